"""The cut: the discrete surface S_h = {phi_h = 0} of a P1 level set on a tetrahedral mesh.

Marching tetrahedra
-------------------
phi_h is the nodal interpolant of the level set.  A tet is *cut* when its nodes do not all lie on
the same side.  Its piece K = S_h ∩ T is planar: a triangle when one node is alone on its side, a
quadrilateral (split into two triangles along a diagonal) when the nodes split two and two.  The
point on an edge (i, j) with phi_i < 0 <= phi_j is ``x_i + t (x_j - x_i)``,
``t = phi_i / (phi_i - phi_j)``.  The piece normal is ``n_h = grad phi_h / |grad phi_h|`` (outward,
towards increasing phi) and every triangle of S_h is oriented by it.

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
the unit sphere) sets the scale.  The band search evaluates the corners of its cells only; every
cell around a node that the snap may zero is among them (its slack bounds the tolerance, see
:func:`_zero_tolerance`), so it snaps exactly the nodes that the full evaluation snaps.  Without
the snap, a node that lies on S mathematically but gets phi = 1e-16 (the paper's torus on its box at
spacing 0.1 has such nodes) gives cut points that coincide with the node in floating point under
different vertex keys: zero-length edges, zero-area triangles and undefined conormals.

Active mesh
-----------
Active tets are the cut tets with a piece of at least three distinct vertices (positive area).  Their
nodes, renumbered 0..n-1 in increasing background id, are the active nodes; ``node_ids`` maps back.
Interior faces are the faces shared by two active tets (``cut.interior_facets(CUT)``); surface
edges are the edges of the pieces (polygons, not the quad diagonals), each shared by the pieces of
two neighbouring tets.

Sides, element sets and measures
--------------------------------
The cut also gives the two sides NEG = {phi_h < 0} and POS of the box, their element sets
(``cut.elements(NEG)``; the cut tets are ``cut.elements(CUT)``), the ghost faces of a side
(``cut.ghost_facets(NEG)``) and the measures ``cut.dx(NEG)``, ``cut.ds()``, ``cut.dF(facets)``:
see :mod:`cutfem.geometry.markers` and :mod:`cutfem.geometry.measures`.  The sides need phi_h at every node of the
background, which the band search does not evaluate; they are computed when first asked for.

Band search
-----------
On a :class:`~cutfem.geometry.box.StructuredBox` with a level set that declares a Lipschitz bound ``L``
(``levelset.lipschitz``; 1 for signed distances), the cut never visits the whole box: blocks of
cells are refined coarse to fine, and a block with centre c and half-diagonal r is dropped when
``|phi(c)| > L r``, which proves phi has no zero there.  Only the cells that survive to the finest
level have their corner values evaluated.  Without a bound every node is evaluated.

A global bound is generous where |grad phi| is small against it (the genus-2 polynomial has
L = 450 on [-2, 2]^3 and |grad phi| between 2 and 16 on S), and the band grows by L / |grad phi| cells.
The local bound: for a user's phi (:class:`~cutfem.geometry.levelset.FunctionLevelSet`) each kept block is
also evaluated on its closed box in interval arithmetic with outward rounding
(:mod:`cutfem.geometry.intervals`); when the enclosure lies above tol or below -tol (the zero rule's snap),
every node of the block keeps one sign after the snap, so none of its cells is cut and the block
is dropped.  This is a proof, not a sample: a cell with a sign change is never dropped by it.
Where phi uses an operation without an interval version, the global bound alone decides.

Trust at the edges: a bound that is too small would drop cut cells silently.  The bound is checked
where it is relied on, at no extra evaluation: each kept block's value against its 8 children's
(centres r / 2 apart) and each band cell's centre value against its 8 corners' (|spacing| / 2
apart); a difference larger than L times the distance raises :class:`CutError` naming the bound
seen.  Every cut then checks that S_h is closed and edge-manifold (every edge of its triangles in
exactly two triangles, from the one-sort edge counts that the Euler characteristic reuses), which
also catches what the samples missed, and raises :class:`CutError` with the likely cause.

Mesh size ``h = N**(-1/3)`` with N the number of background nodes (docs/math.md §2).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from .markers import CUT, NEG, POS, SIDES, ElementSet, FacetSet, interior_facets
from .measures import ElementVolume, FacetMeasure, SideVolume, SurfacePieces
from .box import KUHN_CORNER_COUNTS, KUHN_EDGE_CODES, KUHN_TETS, StructuredBox
from .keys import dense_unique, pair_up, unique_keys
from .mesh import TetMesh, barycentric_gradients, triangle_areas
from .numbering import CUBE_CORNERS, index_dtype
from . import cut_kernels
from . import mesh_kernels

__all__ = ["CutMesh", "cut_mesh", "cut_memory_estimate", "nodal_values", "snapped_nodal_values", "CutError", "NEG", "POS", "CUT"]


class CutError(ValueError):
    """The level set and the background mesh do not give a closed cut surface inside the box."""


# For each sign pattern (bit k set when node k is inside, phi_k < 0) the polygon of the piece as a
# cyclic list of tet edges (i, j) with i inside, j outside; quads have 4 edges, triangles 3.
def _case_table():
    table = {}
    for mask in range(1, 15):
        inside = [k for k in range(4) if mask >> k & 1]
        outside = [k for k in range(4) if not mask >> k & 1]
        if len(inside) == 1:
            i = inside[0]
            edges = [(i, o) for o in outside]
        elif len(inside) == 3:
            o = outside[0]
            edges = [(i, o) for i in inside]
        else:
            a, b = inside
            c, d = outside
            edges = [(a, c), (a, d), (b, d), (b, c)]
        table[mask] = edges
    return table


_CASES = _case_table()


def _case_arrays():
    """Lookup tables indexed by the sign code: edge endpoints (16, 4) and polygon size (16,).
    Triangles repeat their last edge in the fourth slot.  The local node numbers are int8: the
    (m, 4) slot arrays gathered from them are then 8 times smaller than in int64."""
    ei = np.zeros((16, 4), dtype=np.int8)
    ej = np.zeros((16, 4), dtype=np.int8)
    nv = np.zeros(16, dtype=np.int8)
    for code, edges in _CASES.items():
        e = np.array(edges + edges[-1:] * (4 - len(edges)))
        ei[code], ej[code], nv[code] = e[:, 0], e[:, 1], len(edges)
    return ei, ej, nv


_EDGE_I, _EDGE_J, _NVERT = _case_arrays()


def _flip_table():
    """(16,) bool: whether the triangles (0, 1, 2) and (0, 2, 3) of the piece, in the polygon order
    of the case table, turn clockwise about grad phi_h in a positively oriented tet.

    The orientation of the piece's polygon relative to grad phi_h cannot change while the nodal
    values keep their signs (the polygon never degenerates), so it is fixed by the sign code; it is
    read off once on the reference tet with values -1 (inside) and +1 (outside).  In a negatively
    oriented tet it is the opposite."""
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    flip = np.zeros(16, dtype=bool)
    for code, edges in _CASES.items():
        phi = np.where([code >> k & 1 for k in range(4)], -1.0, 1.0)
        p = np.array([x[i] + phi[i] / (phi[i] - phi[j]) * (x[j] - x[i]) for i, j in edges])
        grad = np.linalg.solve(np.c_[x, np.ones(4)], phi)[:3]
        flip[code] = np.dot(np.cross(p[1] - p[0], p[2] - p[0]), grad) < 0
    return flip


_FLIP = _flip_table()


def _as_values_function(levelset):
    """A callable x (..., 3) -> (...) from a LevelSet-like object or a plain callable; a plain
    callable is wrapped in a FunctionLevelSet, whose output-shape check names the fix at the first
    evaluation (e.g. a function written for one point, or returning shape (n, 1))."""
    if hasattr(levelset, "value"):
        return levelset.value
    if callable(levelset):
        from .levelset import FunctionLevelSet

        return FunctionLevelSet(levelset).value
    raise TypeError("levelset must be a LevelSet, a callable f(x) with x of shape (..., 3), or an array of nodal values")


def _enclosure_function(levelset):
    """``enclose(lower (k, 3), upper (k, 3)) -> (lo (k,), hi (k,)) or None``: enclosures of the user's
    phi over boxes by interval arithmetic (:mod:`cutfem.geometry.intervals`), for a FunctionLevelSet or a
    plain callable; None for the other level sets.  After the first failure (phi uses an operation
    with no interval version) it answers None at once: the band search then relies on the global
    Lipschitz bound alone."""
    from .intervals import enclosure
    from .levelset import FunctionLevelSet, LevelSet

    if isinstance(levelset, FunctionLevelSet):
        fn = levelset._value
    elif callable(levelset) and not isinstance(levelset, LevelSet):
        fn = levelset
    else:
        return None
    works = [True]

    def enclose(lower, upper):
        out = enclosure(fn, lower, upper) if works[0] else None
        works[0] = out is not None
        return out

    return enclose


def _enclosed_away(enclose, lower, upper, tol: float):
    """Whether phi is proved to keep one sign on each box [lower, upper] (k, 3): its enclosure
    (``enclose``, see :func:`_enclosure_function`) lies above ``tol`` or below ``-tol`` (the zero
    rule's snap: every value in the box is then nonzero after the snap, of the enclosure's sign).
    All False without an enclosure."""
    out = None if enclose is None else enclose(lower, upper)
    if out is None:
        return np.zeros(len(lower), dtype=bool)
    lo, hi = out
    return (lo > tol) | (hi < -tol)


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
    its tests (:func:`_lipschitz_slack`): it bounds every node's tolerance when L is a true bound
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


# ---------------------------------------------------------------------------------------------
# candidate tets: (global tet ids, global node ids (m,4), coordinates (m,4,3), values (m,4))
# ---------------------------------------------------------------------------------------------


def _mixed(values):
    inside = values < 0
    k = inside.sum(axis=1)
    return (k > 0) & (k < 4)


# A candidate set is (tet ids (m,), node labels (m, 4), nodal values (m, 4), label -> background
# node id (L,) or None when labels are background ids, value of each label (L,)).  Labels are
# increasing with the background ids, so numbering by label is numbering by background id.


def _candidates_full(mesh: TetMesh, values):
    tv = values[mesh.tets]
    cut = np.flatnonzero(_mixed(tv))
    return cut, mesh.tets[cut], tv[cut], None, values


def _spacing_text(box: StructuredBox) -> str:
    s = box.spacing
    return f"{s[0]:g}" if np.all(s == s[0]) else "(" + ", ".join(f"{v:g}" for v in s) + ")"


# ---------------------------------------------------------------------------------------------
# memory: the model of the cut (and of the stages after it), checked before any large allocation
# ---------------------------------------------------------------------------------------------

#: cubes that the surface survey keeps at its finest level, at least (see :func:`_surface_survey`)
SURVEY_BLOCKS = 1 << 14
#: cubes at which the surface survey stops in any case (at most about 2 million evaluations)
SURVEY_MAX_BLOCKS = 1 << 18


def _surface_survey(box: StructuredBox, f, lipschitz: float, enclose=None) -> tuple[float, float]:
    """``(area, edge)``: the area of S as the band search sees it, ``A = L * integral over S of
    1 / |grad phi|`` (the area itself for a signed distance), and the edge of the survey's finest cubes.

    The band search keeps the cells whose centre value is at most L r (r the half-diagonal): a layer
    about 2 r L / |grad phi| thick, so ``|h| A / (hx hy hz)`` cells at spacing h = (hx, hy, hz)
    (:func:`_cut_bytes`).  The survey prunes cubes by the same rule, coarse to fine, and measures
    A = kept b**3 / (2 r_b) = kept b**2 / sqrt(3) on its finest cubes (edge b).  The cubes are those
    of edge 2**k on the lattice anchored at the origin, not at the box's corner: a box has the same
    cubes at every spacing, so its A, and with it the estimate at any spacing, does not depend on
    the spacing the box was made with (the advice at one spacing is the estimate at another).  A
    cube centre outside the box is clipped into it and r grows by the distance clipped (the level
    set is evaluated in the box only).  The survey stops at the first level that keeps
    :data:`SURVEY_BLOCKS` cubes with an A within 10 % of the level above (the surface resolved), at
    :data:`SURVEY_MAX_BLOCKS`, or at cubes a millionth of the box.  Measured against the band
    search's final cells times hx hy hz / |h| (tori R = 1, r = 0.5 and r = 0.1, unit sphere at
    spacings 0.04-0.005, spheres of radius 0.05 and 0.1 at 0.004-0.001): 0.96-1.03 times it, and
    0.92 for the thin torus at 0.04 (five cells across its tube); the same A at every spacing;
    about 60-150 thousand evaluations, 10-50 ms.  Non-finite values keep their cube (the band
    search names them).  With ``enclose`` (:func:`_enclosure_function`) a cube whose enclosure keeps
    one sign is dropped too, as the band search drops it."""
    lo, hi = box.lower.astype(float), box.upper.astype(float)
    extent = float(np.max(hi - lo))
    edge = 2.0 ** np.ceil(np.log2(extent / 8))
    first, stop = np.floor(lo / edge).astype(np.int64), np.ceil(hi / edge).astype(np.int64)
    blocks = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(first, stop)], indexing="ij"), axis=-1).reshape(-1, 3)
    tol = _zero_tolerance(box, lipschitz)
    area = np.inf
    while True:
        centre = (blocks + 0.5) * edge
        point = np.clip(centre, lo, hi)
        r = 0.5 * np.sqrt(3.0) * edge + np.linalg.norm(centre - point, axis=1)
        phi = np.asarray(f(point), dtype=float).reshape(-1)
        keep = ~(np.abs(phi) > _lipschitz_slack(r, lipschitz, tol))
        if enclose is not None and keep.any():
            ids = np.flatnonzero(keep)
            keep[ids[_enclosed_away(enclose, np.clip(blocks[ids] * edge, lo, hi), np.clip((blocks[ids] + 1) * edge, lo, hi), tol)]] = False
        kept = int(np.count_nonzero(keep))
        previous, area = area, kept * edge**2 / np.sqrt(3.0)
        if kept == 0 or kept >= SURVEY_MAX_BLOCKS or edge < 1e-6 * extent or (kept >= SURVEY_BLOCKS and area <= 1.1 * previous):
            return float(area), float(edge)
        edge /= 2
        children = (2 * blocks[keep][:, None, :] + CUBE_CORNERS).reshape(-1, 3)
        blocks = children[np.all((children * edge < hi) & ((children + 1) * edge > lo), axis=1)]


def _cut_bytes(cells, spacing, area, per_tet=None) -> tuple[float, float, float, float]:
    """``(cut, after, band cells, active tets)``: the estimated bytes of the cut of a structured box
    of ``cells`` (3,) at ``spacing`` (3,), of what the stages after it add (0 without ``per_tet``),
    and the band cells and active tets predicted.  ``area``: the surface's area as the band search
    sees it (:func:`_surface_survey`; ``inf`` puts every cell of the box in the band; None: no
    Lipschitz bound, every node is evaluated).

    A fixed part plus parts with their own scaling in the spacing (see :mod:`cutfem.memory`):

    * :data:`~cutfem.memory.CUT_BASE_BYTES`, fixed;
    * :data:`~cutfem.memory.BYTES_PER_BOX_NODE` per node of the box (the band's node bitmap), or
      :data:`~cutfem.memory.BYTES_PER_EVALUATED_NODE` without a bound: spacing**-3;
    * :data:`~cutfem.memory.BYTES_PER_BOUNDARY_NODE` per boundary node (checked one by one without
      a bound, or when the band reaches a face of the box): spacing**-2;
    * :data:`~cutfem.memory.BYTES_PER_BAND_CELL` per band cell, ``BAND_MARGIN |h| area / (hx hy hz)``
      of them (at most every cell): spacing**-2;
    * after the cut, :data:`~cutfem.memory.SOLVE_BASE_BYTES` plus ``per_tet`` per active tet,
      :data:`~cutfem.memory.TETS_PER_BAND_CELL` per band cell (none predicted without a bound:
      :func:`cutfem.problems.common.check_cut_memory` counts them after the cut).

    Every part is non-increasing in the spacing, and so is the estimate."""
    from .. import memory as M

    cells, spacing = np.asarray(cells, dtype=float), np.asarray(spacing, dtype=float)
    n = cells + 1.0
    nodes, boundary = float(np.prod(n)), 2.0 * float(n[0] * n[1] + n[1] * n[2] + n[0] * n[2])
    if area is None:
        return M.CUT_BASE_BYTES + M.BYTES_PER_EVALUATED_NODE * nodes + M.BYTES_PER_BOUNDARY_NODE * boundary, 0.0, float(np.prod(cells)), 0.0
    band = min(float(np.prod(cells)), M.BAND_MARGIN * float(np.linalg.norm(spacing)) * area / float(np.prod(spacing)))
    tets = M.TETS_PER_BAND_CELL * band
    cut = M.CUT_BASE_BYTES + M.BYTES_PER_BOX_NODE * nodes + M.BYTES_PER_BOUNDARY_NODE * boundary + M.BYTES_PER_BAND_CELL * band
    return cut, (0.0 if per_tet is None else M.SOLVE_BASE_BYTES + per_tet * tets), band, tets


def _check_cut_memory(box: StructuredBox, f, lipschitz, per_tet=None, survey=None, enclose=None):
    """Refuse, before anything large is allocated, the cut of ``box`` (and, with ``per_tet``, the
    run after it) when :func:`_cut_bytes` exceeds :func:`cutfem.memory.available_memory`.  Returns
    the survey ``(area, edge)`` that the band search's levels check against (:func:`_band_cells`),
    or None when no survey was needed.

    With a Lipschitz bound the box is first estimated with every cell in the band: when that fits,
    nothing more is done; otherwise the surface is surveyed (:func:`_surface_survey`, or ``survey``
    when given).  The two estimates (the cut; after it, ``SOLVE_BASE_BYTES + per_tet`` per predicted
    active tet, against the same memory as :func:`cutfem.problems.common.check_cut_memory`) are
    checked in turn; a refusal names the spacing at which both fit (:func:`cutfem.memory.
    spacing_that_fits` on the model at t times the spacing, the box two cells longer per axis for
    its rounding to the new spacing), so that the same command at that spacing is not refused,
    here or after the cut, and a spacing 1.3 times finer is."""
    from ..memory import available_memory, check_memory, coarser_spacing_fix

    available = available_memory()[0]
    cells, h = box.cells.astype(float), box.spacing.astype(float)
    if lipschitz is not None and survey is None:
        if max(_cut_bytes(cells, h, np.inf, per_tet)[:2]) <= available:
            return None
        survey = _surface_survey(box, f, float(lipschitz), enclose)
    area = None if lipschitz is None else survey[0]
    cut, after, band, tets = _cut_bytes(cells, h, area, per_tet)
    if cut <= available and after <= available:
        return survey
    fix = coarser_spacing_fix(lambda t: max(_cut_bytes(cells / t + 2.0, h * t, area, per_tet)[:2]), float(np.max(h)), available,
                              " or a smaller box")
    box_text = f"the {' x '.join(map(str, box.cells.tolist()))}-cell box at spacing {_spacing_text(box)}"
    nodes = float(np.prod(box.node_shape.astype(float)))
    if cut > available:
        detail = ("every node evaluated: the level set declares no Lipschitz bound" if area is None
                  else f"{nodes:.3g} nodes, about {band:.3g} cells near the surface")
        check_memory(cut, f"the cut of {box_text} ({detail})", fix)
    check_memory(after, f"the matrices and the solve of about {tets:.3g} active tets (predicted for the cut of {box_text})", fix)


def cut_memory_estimate(background: StructuredBox, levelset, solve_bytes_per_tet: float | None = None) -> tuple[float, float]:
    """``(cut, after)``: the bytes that :func:`cut_mesh` estimates for the cut of the structured box
    ``background`` by ``levelset``, and those that the stages after it add with
    ``solve_bytes_per_tet`` bytes per active tet (0 without).  What :func:`cut_mesh` refuses when it
    exceeds the memory available (it skips the survey when the box fits with every cell in the
    band).  Surveys the surface when the level set declares a Lipschitz bound
    (:func:`_surface_survey`: tens of thousands of evaluations); see :func:`_cut_bytes`."""
    lipschitz = _declared_lipschitz(levelset)
    area = None if lipschitz is None else _surface_survey(background, _as_values_function(levelset), float(lipschitz),
                                                          _enclosure_function(levelset))[0]
    return _cut_bytes(background.cells, background.spacing, area, solve_bytes_per_tet)[:2]


def _lipschitz_slack(dist, lipschitz: float, tol: float):
    """L dist with the slack that keeps rounding from breaking a valid bound (relative 1e-9,
    absolute 1e-14 + the zero rule's tol): what the band search's pruning and its checks compare
    |phi| and |dphi| with."""
    return lipschitz * dist * (1 + 1e-9) + 1e-14 + tol


class _BoundBroken(CutError):
    """A declared Lipschitz bound seen broken; ``ratio`` the largest |phi(x) - phi(y)| / |x - y| seen."""

    def __init__(self, message, ratio):
        super().__init__(message)
        self.ratio = ratio


def _lipschitz_broken(pairs: int, ratio: float, lipschitz: float):
    """The CutError of a broken Lipschitz bound: ``pairs`` evaluated pairs break it, the largest
    |phi(x) - phi(y)| / |x - y| seen is ``ratio``."""
    raise _BoundBroken(
        f"the level set breaks its declared Lipschitz bound L = {lipschitz:g}: between points the band "
        f"search evaluated, |phi(x) - phi(y)| / |x - y| reaches {ratio:.4g} ({pairs} "
        "pairs). The band search drops cells where |phi(centre)| > L r and would leave S_h open. Fix: declare "
        f"a true bound (levelset.lipschitz >= {ratio:.3g}, or None to evaluate every node). A signed distance "
        "to a surface mesh is 1-Lipschitz only when its closed components neither overlap nor intersect: "
        "repair such a mesh (merge the overlapping parts into one closed surface).", ratio
    )


def _mesh_distance_message(levelset, seen: str, crossing_only: bool = False) -> str:
    """The error for the signed distance to a surface mesh (``levelset.mesh``) that is not a
    distance (``seen``: what showed it): nobody declared its bound 1, it is the bound of every
    distance, and a closed mesh whose distance breaks it crosses itself.  With ``crossing_only``, ""
    unless two triangles cross (an open S_h has other causes too).  Names the first pair of
    crossing triangles that share no vertex (found by :func:`cutfem.geometry.surface_checks._crossing_triangles`
    with each triangle its own component: a grid of candidates and exact segment-triangle tests)."""
    from .surface_checks import _crossing_triangles

    points, tri = np.asarray(levelset.mesh.points, dtype=float), np.asarray(levelset.mesh.triangles)
    x = points[tri]
    pairs = _crossing_triangles(points, tri, np.arange(len(tri)), x.min(axis=1), x.max(axis=1))
    apart = ~(tri[pairs[:, 0]][:, :, None] == tri[pairs[:, 1]][:, None, :]).any(axis=(1, 2)) if len(pairs) else np.zeros(0, bool)
    pairs = pairs[apart]
    if len(pairs):
        where = (f"the surface mesh self-intersects: {len(pairs)} pairs of its triangles cross, the first "
                 f"{pairs[0].tolist()} near {np.round(x[pairs[0]].mean(axis=(0, 1)), 6).tolist()}")
    elif crossing_only:
        return ""
    else:
        where = "the surface mesh overlaps or touches itself somewhere (no crossing triangles were found)"
    return (f"the signed distance to the surface mesh is not a distance: {seen}, where a distance changes by at "
            f"most |x - y|. Cause: {where}, so inside and outside are not defined there. Repair the mesh into one "
            "closed surface without self-intersections (e.g. remesh it, or merge the overlapping parts).")


def _band_cells(box: StructuredBox, f, lipschitz: float, tol: float = 0.0, survey=None, enclose=None):
    """Cells that may contain a zero of phi, by coarse-to-fine block pruning.

    Returns ``(cell ids (k,), phi at their centres (k,))``.  A block of ``size`` cells (centre c,
    half-diagonal r = size |spacing| / 2) is dropped when |phi(c)| > L r.  The bound is also
    verified where it is relied on: the centre of each of the 8 children of a kept block lies
    r / 2 from the block's centre, so |phi(child) - phi(parent)| <= L r / 2 must hold; a violation
    raises CutError (see :func:`_lipschitz_broken`) instead of silently dropping cells.  This costs
    one comparison per evaluated centre; it samples the bound, it does not prove it.

    With ``enclose`` (:func:`_enclosure_function`) a block kept by the bound is dropped when phi's
    enclosure over the block's closed box (its cells inside the box) lies above ``tol`` or below
    ``-tol``: every node of its cells then has the enclosure's sign after the zero rule's snap, so
    no cell of the block has corners of both signs (see the module docstring).

    The memory was estimated before the search from a survey of the surface
    (:func:`_check_cut_memory`).  ``survey`` = ``(area, edge, per_tet)``, the survey's area and
    cube edge and the later stages' bytes per active tet, or None (no survey was needed: the box
    fits with every cell in the band).  With it, each level whose blocks are no larger than the
    survey's cubes, before the children of its kept blocks are made, measures the area the same way
    (``kept s**2 hx hy hz / |h|``; 0.99-1.02 times the survey's on the torus, the thin torus and
    the spheres at spacings 0.02-0.001): when it exceeds the survey's by more than the margin
    :data:`~cutfem.memory.BAND_MARGIN` (detail finer than the survey's cubes), the estimate is made
    again with it and a cut that cannot fit is refused.  Coarser levels are not checked: blocks
    much larger than the surface predict up to 2.5 times the final band (a sphere of radius 0.05
    in its box)."""
    from ..memory import BAND_MARGIN

    cells = box.cells
    size = 1
    while size * 4 <= cells.min():
        size *= 2
    nblocks = -(-cells // size)
    blocks = np.stack(np.meshgrid(*[np.arange(n) for n in nblocks], indexing="ij"), axis=-1).reshape(-1, 3)
    blocks = blocks * size  # lower cell index of each block
    half_diag = 0.5 * np.linalg.norm(box.spacing)
    parent_phi = None
    centre = box.coordinates(blocks + 0.5 * size)

    while True:
        phi = np.asarray(f(centre), dtype=float)
        r = half_diag * size
        # keep |phi| <= L r; the children's centres lie r from their parent's: |dphi| <= L r checked
        keep, kept, nonfinite, broken, ratio = cut_kernels.prune_blocks(phi, parent_phi, _lipschitz_slack(r, lipschitz, tol), r)
        if nonfinite:
            _check_finite(phi, "block centres of the band search")
        if broken:
            _lipschitz_broken(broken, ratio, lipschitz)
        if enclose is not None and kept:
            ids = np.flatnonzero(keep)
            first = blocks[ids]
            away = _enclosed_away(enclose, box.coordinates(first), box.coordinates(np.minimum(first + size, cells)), tol)
            keep[ids[away]] = False
            kept -= int(np.count_nonzero(away))
        if survey is not None and size * float(np.max(box.spacing)) <= survey[1]:
            area = kept * float(size) ** 2 * float(np.prod(box.spacing)) / float(np.linalg.norm(box.spacing))
            if area > BAND_MARGIN * survey[0]:
                survey = (area, survey[1], survey[2])
                _check_cut_memory(box, f, lipschitz, survey[2], survey[:2])
        if size == 1:
            break
        size //= 2
        # the children of the kept blocks inside the box, their centres and their parent's value
        blocks, centre, parent_phi = cut_kernels.refine_blocks(blocks, phi, keep, size, cells, box.lower, box.spacing, CUBE_CORNERS)
    # in cell-id order (the search leaves them in block order): the cut's tets then come in id
    # order, so their nodes run through the box layer by layer and the lattice sums over the
    # pieces split into chunks of disjoint node ranges (cutfem.jit.scatter_chunks)
    ids, phi_kept = np.empty(kept, dtype=np.int64), np.empty(kept)
    cut_kernels.kept_cells(np.ascontiguousarray(blocks, dtype=np.int64), phi, keep, int(cells[0]), int(cells[1]), ids, phi_kept)
    phi = phi_kept
    order = np.empty(len(ids), dtype=np.int64)
    mesh_kernels.radix_argsort(ids, int(box.n_cells).bit_length(), order)
    return ids[order], phi[order]


_KUHN_MIXED = (KUHN_CORNER_COUNTS > 0) & (KUHN_CORNER_COUNTS < 4)
"""(256, 6) bool: whether Kuhn tet l of a cell has nodal values of both signs, for each set of
cube corners with phi < 0 (bit c for corner c)."""


def _candidates_structured(box: StructuredBox, f, lipschitz, survey=None, enclose=None):
    """Candidates of a structured box.  With a Lipschitz bound only the corners of the band cells
    (:func:`_band_cells`, which checks the memory at its levels against ``survey``) are evaluated,
    each distinct node once (labels = their rank among those nodes); the corner
    values are checked against the bound (each corner lies r = |spacing| / 2 from its cell's centre,
    see :func:`_band_cells`) in the compiled pass that picks the cut tets
    (:func:`cutfem.geometry.cut_kernels.mixed_kuhn_tets`)."""

    # the cut tets from each cell's corner signs (8 bits) by a table, in one compiled pass that also
    # snaps the corner values and checks them against the bound: the (k, 8) corner values and the
    # (6k, 4) values and nodes of every band tet are never made
    if lipschitz is None:
        cell_ids = np.arange(box.n_cells)
        values = nodal_values(box, f)  # by blocks of nodes, no (N, 3) coordinates
        label_values = _snap_zeros(values, _zero_tolerance(box, None, values))
        label_ids = None
        tet_ids, nodes, vals, _, _ = cut_kernels.mixed_kuhn_tets(label_values, box.cell_corner_ids(cell_ids), cell_ids,
                                                            _KUHN_MIXED, KUHN_TETS)
    else:
        tol = _zero_tolerance(box, lipschitz)  # the band search's slack, not the snap's tolerance
        cell_ids, centre_phi = _band_cells(box, f, float(lipschitz), tol, survey, enclose)
        label_ids, corner = dense_unique(box.cell_corner_ids(cell_ids), box.n_points)
        values = np.asarray(f(box.node_coordinates(label_ids)), dtype=float)
        _check_finite(values, "background nodes near the surface")
        # the snap's tolerance per node from its own band cells: every cell around a node that the
        # snap may zero is in the band (see _zero_tolerance), so this is the tolerance of the full path
        snap = _SNAP * cut_kernels.label_scales(values, corner, _SNAP * float(np.max(np.abs(values), initial=0.0)))
        r = 0.5 * float(np.linalg.norm(box.spacing))  # each corner lies r from its cell's centre
        tet_ids, nodes, vals, broken, ratio = cut_kernels.mixed_kuhn_tets(
            values, corner, cell_ids, _KUHN_MIXED, KUHN_TETS, tol=snap, centre=centre_phi,
            bound=_lipschitz_slack(r, float(lipschitz), tol), dist=r)
        if broken:
            _lipschitz_broken(broken, ratio, float(lipschitz))
        label_values = _snap_zeros(values, snap)
    return tet_ids, nodes, vals, label_ids, label_values


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


def _check_band_boundary(box: StructuredBox, f, band_nodes, band_values):
    """:func:`_check_boundary` after the band search, from one node when the band stays off the
    box's faces.  ``band_nodes`` (increasing ids) and ``band_values`` (snapped by the zero rule):
    the nodes the band search evaluated.  Every tet with nodes of both signs (after the snap) lies
    in a band cell, so when no band node is on the boundary, no boundary edge joins a node with
    phi < 0 to one without, and as the boundary of a box is connected its nodes are all inside or
    all outside: the first node decides (all inside: the full check words the error).  Otherwise
    every boundary node is checked, the band's with their snapped values (the cut's own signs),
    the others with their values: a node outside every band cell has |phi| above the band search's
    slack, which bounds the snap's tolerance, so the snap leaves it as it is.  At spacing 0.003125
    the boundary has 6 million nodes (0.6 s)."""

    n = [int(v) for v in box.node_shape]
    if not mesh_kernels.box_ids_on_faces(np.ascontiguousarray(band_nodes, dtype=np.int64), *n):
        first = np.asarray(f(box.node_coordinates(np.zeros(1, dtype=np.int64))), dtype=float).reshape(-1)
        _check_finite(first, "boundary nodes")
        if first[0] >= 0:
            return
    b = box.boundary_nodes
    vb = np.asarray(f(box.node_coordinates(b)), dtype=float).reshape(-1)
    _check_finite(vb, "boundary nodes")
    at = np.minimum(np.searchsorted(band_nodes, b), max(len(band_nodes) - 1, 0))
    in_band = band_nodes[at] == b if len(band_nodes) else np.zeros(len(b), dtype=bool)
    vb[in_band] = band_values[at[in_band]]
    _check_boundary(box, f, boundary_values=vb)


# ---------------------------------------------------------------------------------------------
# the cut mesh
# ---------------------------------------------------------------------------------------------


@dataclass(eq=False)
class CutMesh:
    """S_h and the active mesh T_h of a P1 level set on a background tetrahedral mesh.

    Active mesh (n active tets, p active nodes):
        ``node_ids`` (p,) background ids; ``points`` (p, 3); ``values`` (p,) phi_h;
        ``tets`` (n, 4) local node indices; ``tet_ids`` (n,) background tet ids;
        ``normals`` (n, 3) n_h per piece; ``piece_areas`` (n,).
    Surface S_h (V vertices, T triangles):
        ``vertices`` (V, 3); ``triangles`` (T, 3) oriented by n_h; ``triangle_tets`` (T,) active tet
        of each triangle.
    Mesh size ``h = N**(-1/3)`` of the background mesh; ``background`` is the background mesh.
    """

    background: TetMesh
    node_ids: np.ndarray
    points: np.ndarray
    values: np.ndarray
    tets: np.ndarray
    tet_ids: np.ndarray
    normals: np.ndarray
    vertices: np.ndarray
    triangles: np.ndarray
    triangle_tets: np.ndarray
    _gradients: tuple | None = field(default=None, repr=False)  # (basis gradients, volumes) if known
    levelset: object = field(default=None, repr=False)  # what was cut: for the sides' nodal values

    # -- sides, element sets, facet sets and measures (cutfem.geometry.markers, cutfem.geometry.measures) ------------
    @cached_property
    def background_values(self) -> np.ndarray:
        """(N,) phi_h at every background node with the zero rule's snap (visits every node; the
        sides need them, S_h alone does not)."""
        if self.levelset is None:
            raise ValueError("this cut was made without its level set; cut with cut_mesh(background, levelset)")
        return snapped_nodal_values(self.background, self.levelset)

    @cached_property
    def _element_sets(self) -> dict:
        return {}

    def elements(self, which=CUT):
        """The element set ``NEG``, ``POS`` or ``CUT`` (:class:`cutfem.geometry.markers.ElementSet`, cached).

        NEG (POS): the tets with a part of positive volume on that side, and the cut tets; CUT: the
        tets that carry a piece of S_h.  See :mod:`cutfem.geometry.markers`."""
        if isinstance(which, ElementSet):
            return which
        sets = self._element_sets
        if which not in sets:
            if which == CUT:
                sets[CUT] = ElementSet(self.background, self.tet_ids, name=CUT, cut=self, tets=self.tets, node_ids=self.node_ids,
                                       points=self.points, gradients=self._grads_volumes[0], volumes=self._grads_volumes[1], normals=self.normals)
            elif which in SIDES:
                v, bg = self.background_values, self.background
                mark = bg.tet_node_counts(v < 0) > 0 if which == NEG else (bg.tet_node_counts(v > 0) > 0) | (bg.tet_node_counts(v == 0) == 4)
                mark[self.tet_ids] = True
                sets[which] = ElementSet(self.background, np.flatnonzero(mark), name=which, cut=self)
            else:
                raise ValueError(f"element sets of a cut are NEG, POS and CUT; got {which!r}")
        return sets[which]

    def interior_facets(self, which=CUT) -> FacetSet:
        """The faces shared by two tets of an element set (default: the cut tets, the faces of J_F)."""
        return self.elements(which).interior_facets

    def ghost_facets(self, side) -> FacetSet:
        """The ghost-penalty faces of a side: interior faces of its element set with at least one
        tet cut (for the bulk ghost penalty of docs/math.md §7)."""

        es = self.elements(side)
        cut_mark = np.zeros(es.n_elements, dtype=bool)
        cut_mark[es.locate(self.tet_ids, "the cut tets")] = True
        # both tets of such a face touch a node of a cut tet: look for faces only among those tets
        # (a band around Gamma_h) instead of sorting every face of the side; the band in one compiled
        # pass (numpy's gather of every tet's four flags took 0.085 s at spacing 0.02, 3.9 million tets)
        near = np.empty(es.n_elements, dtype=bool)
        cut_kernels.tets_near(es.tets, cut_mark, es.n_nodes, near)
        band = np.flatnonzero(near)
        kuhn = es.kuhn_types
        pairs, opposite = interior_facets(es.tets[band], es.n_nodes, None if kuhn is None else kuhn[band])
        pairs = band[pairs]
        keep = cut_mark[pairs[:, 0]] | cut_mark[pairs[:, 1]]
        return FacetSet(es, pairs[keep], opposite[keep], name=f"ghost faces of {side}")

    @cached_property
    def _measures(self) -> dict:
        return {}

    def ds(self):
        """The measure on S_h = Gamma_h (:class:`cutfem.geometry.measures.SurfacePieces`), normal from NEG to POS."""
        if "ds" not in self._measures:
            self._measures["ds"] = SurfacePieces(self)
        return self._measures["ds"]

    def dx(self, where=NEG):
        """The volume measure of a side (``NEG``/``POS``: the cut volume parts,
        :class:`~cutfem.geometry.measures.SideVolume`) or of an element set (whole tets,
        :class:`~cutfem.geometry.measures.ElementVolume`)."""
        key = ("dx", where if isinstance(where, str) else id(where))
        if key not in self._measures:
            if isinstance(where, str) and where in SIDES:
                self._measures[key] = SideVolume(self, where)
            else:
                self._measures[key] = ElementVolume(self.elements(where))
        return self._measures[key]

    def dF(self, facets):
        """The facet measure of a facet set (:class:`~cutfem.geometry.measures.FacetMeasure`)."""
        if not isinstance(facets, FacetSet):
            raise TypeError(f"dF takes a FacetSet (cut.interior_facets(...), cut.ghost_facets(...), or a subset of one), "
                            f"got {type(facets).__name__}")
        key = ("dF", id(facets))
        if key not in self._measures:
            self._measures[key] = FacetMeasure(facets)
        return self._measures[key]

    # -- sizes -----------------------------------------------------------------------------
    @property
    def h(self) -> float:
        """Global mesh size N**(-1/3), N = number of background nodes (:attr:`TetMesh.h`)."""
        return self.background.h

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    @property
    def n_nodes(self) -> int:
        return len(self.points)

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    # -- geometry of S_h ---------------------------------------------------------------------
    @property
    def triangle_points(self) -> np.ndarray:
        """(T, 3, 3) vertex coordinates of each triangle of S_h (gathered on each access, not kept:
        80 MB at a million triangles)."""
        return self.vertices[self.triangles]

    @cached_property
    def triangle_areas(self) -> np.ndarray:
        return triangle_areas(self.vertices, self.triangles)

    @cached_property
    def piece_areas(self) -> np.ndarray:
        """(n,) area of the piece K in each active tet."""
        return np.bincount(self.triangle_tets, weights=self.triangle_areas, minlength=self.n_tets)

    @property
    def area(self) -> float:
        """Area of S_h."""
        return float(self.triangle_areas.sum())

    @cached_property
    def enclosed_volume(self) -> float:
        """Volume enclosed by S_h, by the divergence theorem (1/3) ∫ (x - o)·n: per triangle
        (1/6) a·(b x c), the vertices measured from the mean o of the vertices of S_h (the sum does
        not depend on o on a closed surface; from the origin, a mesh 1e4 away from it in its own
        units lost 3 digits: terms of 1e13 for a volume of 1)."""
        p = self.triangle_points - self.vertices.mean(axis=0)
        return float(np.einsum("ij,ij->", p[:, 0], np.cross(p[:, 1], p[:, 2])) / 6.0)

    @cached_property
    def _edge_census(self) -> tuple:
        """(E, B): the number of distinct edges of the triangles of S_h and how many of them are not
        in exactly two triangles (:func:`cutfem.geometry.cut_kernels.edge_census`, one compiled pass; two
        numbers are kept, not a count per edge)."""

        return cut_kernels.edge_census(self.triangles, len(self.vertices))

    @property
    def euler_characteristic(self) -> int:
        """V - E + F of the triangulated S_h."""
        return len(self.vertices) - self._edge_census[0] + self.n_triangles

    @property
    def is_closed(self) -> bool:
        """Every triangle edge of S_h is shared by exactly two triangles."""
        return self._edge_census[1] == 0

    # -- active mesh -------------------------------------------------------------------------
    @cached_property
    def tet_vertices(self) -> np.ndarray:
        """(n, 4, 3) coordinates of the active tets."""
        return self.points[self.tets]

    @cached_property
    def _grads_volumes(self):
        if self._gradients is not None:
            return self._gradients
        grads, vol = barycentric_gradients(self.tet_vertices)
        return grads, np.abs(vol)

    @property
    def basis_gradients(self) -> np.ndarray:
        """(n, 4, 3) gradients of the P1 basis functions on each active tet (on a structured box read
        off the Kuhn table on each access, not kept: see :attr:`cutfem.geometry.markers.ElementSet.gradients`)."""
        return self.elements(CUT).gradients

    @property
    def tet_volumes(self) -> np.ndarray:
        """(n,) volumes of the active tets (on a structured box built on each access, not kept: see
        :attr:`cutfem.geometry.markers.ElementSet.volumes`)."""
        return self.elements(CUT).volumes

    # -- edges of S_h shared by pieces of neighbouring tets -----------------------------------
    @cached_property
    def _surface_edges(self):
        """The edges of the pieces' polygons from the triangles: an edge held by two triangles of
        different tets (a quadrilateral's diagonal is held by two triangles of one tet and is left
        out).  Edges in increasing (lower, upper) vertex order, the two tets in increasing order
        (the triangles are in tet order)."""
        t = self.triangles
        nxt = np.roll(t, -1, axis=1)  # half-edge k of triangle T, from vertex k to k + 1, at 3T + k
        lo = np.minimum(t, nxt).reshape(-1).astype(np.int64)
        hi = np.maximum(t, nxt).reshape(-1).astype(np.int64)
        order, starts, counts = pair_up(lo * len(self.vertices) + hi)
        if np.any(counts != 2):
            bad = int(np.sum(counts != 2))
            warnings.warn(
                f"{bad} edges of S_h are not shared by exactly two pieces (the zero set touches itself); "
                "they are left out of the edge stabilization",
                RuntimeWarning,
                stacklevel=3,
            )
        two = starts[counts == 2]
        a, b = order[two], order[two + 1]
        tets = np.stack([self.triangle_tets[a // 3], self.triangle_tets[b // 3]], axis=1)
        between = tets[:, 0] != tets[:, 1]
        a = a[between]
        return np.stack([lo[a], hi[a]], axis=1), tets[between]

    @property
    def surface_edges(self) -> np.ndarray:
        """(E, 2) vertex indices of the edges of S_h between the pieces of two tets."""
        return self._surface_edges[0]

    @property
    def surface_edge_tets(self) -> np.ndarray:
        """(E, 2) the active tets whose pieces share each surface edge."""
        return self._surface_edges[1]

    @cached_property
    def surface_edge_conormals(self) -> np.ndarray:
        """(E, 2, 3) t_{E,K}: unit, in the plane of piece K, orthogonal to E, pointing out of K."""
        e = self.surface_edges
        p0, p1 = self.vertices[e[:, 0]], self.vertices[e[:, 1]]
        d = p1 - p0
        out = np.empty((len(e), 2, 3))
        # centroid of each piece from its triangles
        cent = np.zeros((self.n_tets, 3))
        cnt = np.bincount(self.triangle_tets, minlength=self.n_tets).astype(float)
        tc = self.triangle_points.mean(axis=1)
        for k in range(3):
            cent[:, k] = np.bincount(self.triangle_tets, weights=tc[:, k], minlength=self.n_tets)
        cent /= cnt[:, None]
        for s in range(2):
            t = np.cross(d, self.normals[self.surface_edge_tets[:, s]])
            t /= np.linalg.norm(t, axis=1)[:, None]
            sign = np.sign(np.einsum("ij,ij->i", t, 0.5 * (p0 + p1) - cent[self.surface_edge_tets[:, s]]))
            out[:, s] = t * sign[:, None]
        return out

    @cached_property
    def surface_edge_lengths(self) -> np.ndarray:
        e = self.surface_edges
        return np.linalg.norm(self.vertices[e[:, 1]] - self.vertices[e[:, 0]], axis=1)

    def to_pyvista(self):
        """S_h as a ``pyvista.PolyData`` (cell data: parent tet)."""
        import pyvista as pv

        faces = np.hstack([np.full((self.n_triangles, 1), 3), self.triangles]).ravel()
        poly = pv.PolyData(self.vertices, faces)
        poly.cell_data["tet"] = self.triangle_tets
        return poly

    def active_mesh_pyvista(self):
        """The active tets as a ``pyvista.UnstructuredGrid``."""
        import pyvista as pv

        return pv.UnstructuredGrid({pv.CellType.TETRA: self.tets}, self.points)

    def __repr__(self) -> str:
        return (
            f"CutMesh(active_tets={self.n_tets}, active_nodes={self.n_nodes}, triangles={self.n_triangles}, "
            f"area={self.area:.6g}, h={self.h:.4g})"
        )


# the polygon slots of the triangles (0, 1, 2) and (0, 2, 3) of a piece, and the same turned over
_TRIANGLE_SLOTS = np.array([[0, 1, 2, 0, 2, 3], [0, 2, 1, 0, 3, 2]], dtype=np.int64)


def _marching(tet_ids, labels, vals):
    """Marching tetrahedra on the candidate (cut) tets, tet by tet; see the module docstring.

    The polygon slots of a tet are the edges (i, j) (i inside, j outside) of the case table of its
    sign code (bit k: node k inside); a slot is the point ``x_i + t (x_j - x_i)``,
    ``t = phi_i / (phi_i - phi_j)``, or the node j itself when phi_j == 0.  Two slots of a tet are
    the same vertex when they are the same node or the same edge; a tet whose piece has fewer than
    three distinct vertices (it collapsed to a point or a segment) is dropped.  One compiled pass
    (:func:`cutfem.geometry.cut_kernels.marching`) that compacts the three arrays in place; returns
    ``(tet_ids, labels, vals, code)`` of the kept tets."""

    n, code = cut_kernels.marching(tet_ids, labels, vals, _EDGE_I, _EDGE_J)
    return tet_ids[:n], labels[:n], vals[:n], code


def cut_mesh(background: TetMesh, levelset, *, check_boundary: bool = True, solve_bytes_per_tet: float | None = None) -> CutMesh:
    """Cut a background tetrahedral mesh by the zero level set of the P1 interpolant of ``levelset``.

    ``levelset``: a LevelSet (``value``, optional ``lipschitz``), a callable ``f(x)`` with x (..., 3),
    or an array of nodal values (N,) (not with a structured box's band search).
    Raises :class:`CutError` when the level set does not cut the mesh, the surface reaches the box
    boundary (unless ``check_boundary=False``), the declared Lipschitz bound is seen to be broken
    (:func:`_band_cells`) or S_h is not closed and edge-manifold (:func:`_check_closed`: every
    edge of its triangles in exactly two triangles; with ``check_boundary=False`` S_h may end on
    the faces of the box); ValueError for NaN/inf values.  See the module docstring for the zero rule.

    :class:`cutfem.memory.InsufficientMemoryError` is raised before any large allocation when the
    cut of a structured box would not fit in memory (:func:`cut_memory_estimate`), naming a spacing
    that fits.  ``solve_bytes_per_tet``: what the stages after the cut (space, matrices, solve) add
    per active tet, as :func:`cutfem.problems.common.check_cut_memory` counts it.  When given (the
    problems give theirs), the cut also refuses up front a spacing whose later stages would not fit,
    from the active tets it predicts, and its advice is a spacing at which the cut and those stages
    both fit: one estimate before the cut, with its one advice, instead of a cut that is made and then
    refused.  The check after the cut, on the real active tets, stays for what the prediction does not
    cover (no Lipschitz bound, unstructured backgrounds).
    """
    lipschitz = _declared_lipschitz(levelset)
    mesh_distance = getattr(levelset, "is_distance", False) and getattr(levelset, "mesh", None) is not None
    structured = isinstance(background, StructuredBox)
    band = structured and lipschitz is not None and not isinstance(levelset, np.ndarray)  # band search used
    if isinstance(levelset, np.ndarray):
        values = nodal_values(background, levelset)
        values = _snap_zeros(values, _zero_tolerance(background, None, values))
        if check_boundary:
            _check_boundary(background, values)
        cand = _candidates_full(background, values)
    elif structured:
        f = _as_values_function(levelset)
        enclose = _enclosure_function(levelset) if band else None
        survey = _check_cut_memory(background, f, lipschitz, solve_bytes_per_tet, enclose=enclose)
        try:
            cand = _candidates_structured(background, f, lipschitz, None if survey is None else (*survey, solve_bytes_per_tet), enclose)
        except _BoundBroken as exc:
            if mesh_distance:  # its bound 1 is no declaration of the user's: say what is wrong with the mesh
                raise CutError(_mesh_distance_message(
                    levelset, f"|phi(x) - phi(y)| / |x - y| reaches {exc.ratio:.3g} between points the cut evaluated")) from None
            raise
        if check_boundary and band:
            _check_band_boundary(background, f, cand[3], cand[4])
        elif check_boundary:
            _check_boundary(background, cand[4])  # every node's snapped value: the cut's own signs
    else:
        values = nodal_values(background, levelset)
        values = _snap_zeros(values, _zero_tolerance(background, lipschitz, values))
        if check_boundary:
            _check_boundary(background, values)
        cand = _candidates_full(background, values)
    tet_ids, labels, vals, label_ids, label_values = cand
    if len(tet_ids) == 0:
        touching = _touching_only(background, label_ids, label_values)
        if touching:
            raise CutError(touching)
        raise CutError(
            "the level set does not cut the background mesh: no tetrahedron has nodal values of both signs. "
            "Check that the surface lies inside the box and is larger than a cell (refine the mesh), and that "
            "the level set is negative inside."
            + (" With the band search, also check that the declared Lipschitz bound (levelset.lipschitz) is "
               "a true bound." if band else "")
        )
    tet_ids, labels, vals, code = _marching(tet_ids, labels, np.ascontiguousarray(vals, dtype=float))
    del cand
    if len(tet_ids) == 0:
        raise CutError(
            "every piece of the cut collapsed to a point or a segment: the level set is negative only at nodes "
            "whose pieces have no area (its zero set meets the mesh in points or lines). Refine the background mesh "
            "if the surface is smaller than a cell; if it touches the box only on its boundary, move the box or "
            "the level set so that the surface lies inside the box.")
    m = len(tet_ids)

    # active nodes, numbered by increasing background id (labels increase with it); the tets' node
    # numbers int32 while they fit (209 MB less for the 13.7 million cut tets at spacing 0.003125)
    uniq, tets = dense_unique(labels, len(label_values))
    del labels
    node_ids = uniq if label_ids is None else label_ids[uniq]
    points = background.node_coordinates(node_ids) if structured else background.points[node_ids]
    values = label_values[uniq]
    p = len(node_ids)

    # basis gradients: the Kuhn table on a structured box (never kept: see ElementSet.gradients),
    # else from the vertices; normals n_h = grad phi_h / |grad phi_h| by a compiled pass

    if structured:
        grads = volumes = None  # every tet has the box's volume (see ElementSet.volumes)
        negative = None
        table, types = background.gradient_table, mesh_kernels.kuhn_types(tet_ids)
    else:
        grads, volumes = barycentric_gradients(points[tets])
        negative = volumes < 0
        volumes = np.abs(volumes)
        table, types = grads, np.arange(m)
    normals = np.empty((m, 3))
    cut_kernels.level_set_normals(vals, table, types, normals)
    if not np.isfinite(normals).all():  # grad phi_h = 0 or not finite: values beyond floating point (the kernel rescales the rest)
        bad = ~np.isfinite(normals).all(axis=1)
        big = float(np.max(np.abs(vals)))
        raise CutError(f"the normals n_h = grad phi_h / |grad phi_h| of {int(np.count_nonzero(bad))} cut tets are not "
                       f"finite: the level set's values (up to {big:.3g} in the cut tets) are too large or too small for "
                       "floating point. Scale the level set to values of the order of the distance to its zero set.")

    # surface vertices: key = active node (on-node vertex) or an edge key, numbered by key.  On a
    # structured box the lattice edge {v, v + e_S} (v = min: the active nodes increase with the
    # background ids) has the key p - 1 + 7 v + c(S) in [p, 8p), ordered as (v, max) (see
    # box.KUHN_EDGE_CODES): numbered by a marker array, with no sort
    key = cut_kernels.slot_keys(tets, code, vals, _EDGE_I, _EDGE_J, p, lattice=(KUHN_EDGE_CODES, types) if structured else None)
    del types
    vkeys, vinv = dense_unique(key, 8 * p) if structured else unique_keys(key.reshape(-1), return_inverse=True)
    n_vertices = len(vkeys)
    del key, vkeys
    # vertex numbers (and so the triangles) as int32 while they fit: 12 bytes a triangle, 16 a tet less
    vinv = vinv.astype(index_dtype(n_vertices), copy=False).reshape(m, 4)
    # each vertex computed once, from its first slot; triangles (0,1,2) and, for quads, (0,2,3),
    # tet by tet, without those with repeated vertices; orientation by n_h from the sign code (see
    # _flip_table)
    vertices, tri, tri_tet = cut_kernels.surface(vinv, n_vertices, tets, code, vals, points, _EDGE_I, _EDGE_J, _NVERT, _FLIP,
                                             _TRIANGLE_SLOTS, negative=negative)
    del vals, vinv

    cm = CutMesh(
        levelset=levelset,
        background=background,
        node_ids=node_ids,
        points=points,
        values=values,
        tets=tets,
        tet_ids=tet_ids,
        normals=normals,
        vertices=vertices,
        triangles=tri,
        triangle_tets=tri_tet,
        _gradients=(grads, volumes),  # None on a structured box: the Kuhn table and the box's tet volume serve them
    )
    try:
        _check_closed(cm, check_boundary, band)
    except CutError:
        crossing = _mesh_distance_message(levelset, "the cut surface S_h is not closed", True) if mesh_distance else ""
        if crossing:
            raise CutError(crossing) from None
        raise
    return cm


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


def _touching_only(mesh: TetMesh, label_ids, label_values) -> str:
    """The message for a level set that is zero at some nodes and negative at none (no cut tet): its
    zero set meets the mesh in a set of zero area (a plane through an edge, a corner or a face of the
    box, a surface touching the box from outside), where no refinement can help; "" otherwise."""
    values = np.asarray(label_values)
    zero = values == 0
    if not np.any(zero) or np.any(values < 0):
        return ""
    ids = np.flatnonzero(zero) if label_ids is None else np.asarray(label_ids)[zero]
    if isinstance(mesh, StructuredBox):
        nx, ny, nz = (int(n) for n in mesh.node_shape)
        i, j, k = ids % nx, (ids // nx) % ny, ids // (nx * ny)
        on = (i == 0) | (i == nx - 1) | (j == 0) | (j == ny - 1) | (k == 0) | (k == nz - 1)
        x = mesh.node_coordinates(ids[:1])[0]
    else:
        on = np.isin(ids, mesh.boundary_nodes)
        x = mesh.points[ids[0]]
    n = f"{ids.size} node{'s' if ids.size != 1 else ''} (first at {np.round(x, 6).tolist()})"
    if np.all(on):
        return (f"the level set does not cut the background mesh: it is zero at {n}, all on the boundary of the mesh, "
                "and negative at none: it touches the box only on its boundary (its zero set meets the box in a point, "
                "a line or a face, a set of zero area, with phi >= 0 inside the box), so S_h is empty and refining the "
                "mesh cannot help. Move the box or the level set so that the surface lies inside the box, with phi < 0 "
                "inside the surface.")
    return (f"the level set does not cut the background mesh: it is zero at {n}, {int(np.count_nonzero(on))} of them on "
            "the boundary of the mesh, and negative at none: its zero set meets the mesh only in a set of zero area "
            "(phi >= 0 on both sides of it, e.g. abs(x) or a surface touching nodes from outside), so S_h is empty. A "
            "level set must be negative inside the surface; refine the mesh only if the surface is smaller than a cell.")


def _check_closed(cut: CutMesh, check_boundary: bool, band: bool) -> None:
    """Raise CutError unless S_h is closed and edge-manifold: every edge of its triangles in
    exactly two triangles.

    Uses the edge census of :attr:`CutMesh._edge_census` (one compiled pass, cached: the Euler
    characteristic and ``is_closed`` reuse it).  With ``check_boundary=False`` the surface may
    leave the box: an edge in one triangle is then accepted when both its ends lie on the faces of
    the background's bounding box (within 1e-9 of its diagonal).  The P1 zero set of values at
    every node is always closed inside the mesh, so an open S_h means that the band search
    (``band``) dropped cut cells: phi changes faster than its declared Lipschitz bound somewhere
    it was not sampled (see :func:`_band_cells`)."""
    if cut.is_closed:
        return
    t = cut.triangles
    V = len(cut.vertices)
    e = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]).astype(np.int64)
    keys = np.minimum(e[:, 0], e[:, 1]) * V + np.maximum(e[:, 0], e[:, 1])
    order, starts, counts = pair_up(keys)
    edges = e[order[starts]]
    open_ = counts == 1
    if not check_boundary and np.any(open_):
        lo, hi = (np.asarray(b, float) for b in cut.background.bounds)
        eps = 1e-9 * float(np.linalg.norm(hi - lo))
        x = cut.vertices[edges[open_]]  # (k, 2, 3)
        on_face = np.any((np.abs(x - lo) <= eps) | (np.abs(x - hi) <= eps), axis=2)
        open_[np.flatnonzero(open_)[np.all(on_face, axis=1)]] = False
    many = counts > 2
    if not (np.any(open_) or np.any(many)):
        return
    first = edges[open_ | many][0]
    where = cut.vertices[first].mean(axis=0)
    cause = (
        "the level set changes faster than its declared Lipschitz bound (levelset.lipschitz), so the band "
        "search dropped cut cells: declare a true bound, or None to evaluate every node"
        if band
        else "the zero set of phi_h touches or crosses itself: refine the background mesh or move the level set"
    )
    raise CutError(
        f"the cut surface S_h is not a closed manifold: {int(open_.sum())} edges lie in one triangle only and "
        f"{int(many.sum())} in more than two (first near {np.round(where, 6).tolist()}). Likely cause: {cause}. "
        "A signed distance to a surface mesh whose closed components overlap or intersect (for example a model "
        "made of overlapping parts) has this defect too: repair the mesh into one closed surface without "
        "self-intersections."
    )


def snapped_nodal_values(mesh: TetMesh, levelset) -> np.ndarray:
    """phi_h at every node of ``mesh`` as the cut sees it: :func:`nodal_values` with the values of
    modulus at most 1e-12 max |phi| over the node and its neighbours set to exactly 0 (the zero
    rule, :func:`_zero_tolerance`).  Visits every node; for handing the same
    discrete level set to other codes and for volume integrals."""
    values = nodal_values(mesh, levelset)
    return _snap_zeros(values, _zero_tolerance(mesh, None, values))
