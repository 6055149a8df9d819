"""The band search: the cut tets of a structured box without visiting the whole box.

On a :class:`~cutfem.geometry.box.StructuredBox` with a level set that declares a Lipschitz bound ``L``
(``levelset.lipschitz``; 1 for signed distances), the cut never visits the whole box: blocks of
cells are refined coarse to fine, and a block with centre c and half-diagonal r is dropped when
``|phi(c)| > L r``, which proves phi has no zero there.  Only the cells that survive to the finest
level have their corner values evaluated, and the cut tets are picked from each cell's corner signs
by a table (:func:`_candidates_structured`).  Without a bound every node is evaluated.

A global bound is generous where |grad phi| is small against it (the genus-2 polynomial has
L = 450 on [-2, 2]^3 and |grad phi| between 2 and 16 on S), and the band grows by L / |grad phi| cells.
The local bound: for a user's phi (:class:`~cutfem.geometry.levelset.FunctionLevelSet`) each kept block is
also evaluated on its closed box in interval arithmetic with outward rounding
(:mod:`cutfem.geometry.intervals`); when the enclosure lies above tol or below -tol (the zero rule's snap,
:mod:`cutfem.geometry.nodal_values`), every node of the block keeps one sign after the snap, so none
of its cells is cut and the block is dropped.  This is a proof, not a sample: a cell with a sign
change is never dropped by it.  Where phi uses an operation without an interval version, the global
bound alone decides.

Trust at the edges: a bound that is too small would drop cut cells silently.  The bound is checked
where it is relied on, at no extra evaluation: each kept block's value against its 8 children's
(centres r / 2 apart) and each band cell's centre value against its 8 corners' (|spacing| / 2
apart); a difference larger than L times the distance raises :class:`~cutfem.geometry.nodal_values.CutError`
naming the bound seen.  The cut then checks that S_h is closed (:mod:`cutfem.geometry.cut`), which
also catches what the samples missed.

Memory: before any large allocation the cut of the box (and, when given, the stages after it) is
estimated from a survey of the surface and refused when it does not fit, naming a spacing that does
(:func:`cut_memory_estimate`, :func:`_check_cut_memory`; the model's parts are in :mod:`cutfem.memory`).
"""

from __future__ import annotations

import numpy as np

from .. import memory
from .box import KUHN_CORNER_COUNTS, KUHN_TETS, StructuredBox
from .intervals import enclosure
from .keys import dense_unique
from .levelset import FunctionLevelSet, LevelSet
from .nodal_values import (
    _SNAP,
    CutError,
    _as_values_function,
    _check_boundary,
    _check_finite,
    _declared_lipschitz,
    _snap_zeros,
    _zero_tolerance,
    nodal_values,
)
from .numbering import CUBE_CORNERS
from . import cut_kernels
from . import mesh_kernels

__all__ = ["cut_memory_estimate", "SURVEY_BLOCKS", "SURVEY_MAX_BLOCKS"]


def _enclosure_function(levelset):
    """``enclose(lower (k, 3), upper (k, 3)) -> (lo (k,), hi (k,)) or None``: enclosures of the user's
    phi over boxes by interval arithmetic (:mod:`cutfem.geometry.intervals`), for a FunctionLevelSet or a
    plain callable; None for the other level sets.  After the first failure (phi uses an operation
    with no interval version) it answers None at once: the band search then relies on the global
    Lipschitz bound alone."""
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
    cells, spacing = np.asarray(cells, dtype=float), np.asarray(spacing, dtype=float)
    n = cells + 1.0
    nodes, boundary = float(np.prod(n)), 2.0 * float(n[0] * n[1] + n[1] * n[2] + n[0] * n[2])
    if area is None:
        cut = memory.CUT_BASE_BYTES + memory.BYTES_PER_EVALUATED_NODE * nodes + memory.BYTES_PER_BOUNDARY_NODE * boundary
        return cut, 0.0, float(np.prod(cells)), 0.0
    band = min(float(np.prod(cells)), memory.BAND_MARGIN * float(np.linalg.norm(spacing)) * area / float(np.prod(spacing)))
    tets = memory.TETS_PER_BAND_CELL * band
    cut = (memory.CUT_BASE_BYTES + memory.BYTES_PER_BOX_NODE * nodes + memory.BYTES_PER_BOUNDARY_NODE * boundary
           + memory.BYTES_PER_BAND_CELL * band)
    return cut, (0.0 if per_tet is None else memory.SOLVE_BASE_BYTES + per_tet * tets), band, tets


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
    available = memory.available_memory()[0]
    cells, h = box.cells.astype(float), box.spacing.astype(float)
    if lipschitz is not None and survey is None:
        if max(_cut_bytes(cells, h, np.inf, per_tet)[:2]) <= available:
            return None
        survey = _surface_survey(box, f, float(lipschitz), enclose)
    area = None if lipschitz is None else survey[0]
    cut, after, band, tets = _cut_bytes(cells, h, area, per_tet)
    if cut <= available and after <= available:
        return survey
    fix = memory.coarser_spacing_fix(lambda t: max(_cut_bytes(cells / t + 2.0, h * t, area, per_tet)[:2]), float(np.max(h)),
                                     available, " or a smaller box")
    box_text = f"the {' x '.join(map(str, box.cells.tolist()))}-cell box at spacing {_spacing_text(box)}"
    nodes = float(np.prod(box.node_shape.astype(float)))
    if cut > available:
        detail = ("every node evaluated: the level set declares no Lipschitz bound" if area is None
                  else f"{nodes:.3g} nodes, about {band:.3g} cells near the surface")
        memory.check_memory(cut, f"the cut of {box_text} ({detail})", fix)
    memory.check_memory(after, f"the matrices and the solve of about {tets:.3g} active tets (predicted for the cut of {box_text})",
                        fix)


def cut_memory_estimate(background: StructuredBox, levelset, solve_bytes_per_tet: float | None = None) -> tuple[float, float]:
    """``(cut, after)``: the bytes that :func:`~cutfem.geometry.cut.cut_mesh` estimates for the cut of the structured box
    ``background`` by ``levelset``, and those that the stages after it add with
    ``solve_bytes_per_tet`` bytes per active tet (0 without).  What :func:`~cutfem.geometry.cut.cut_mesh` refuses when it
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
            if area > memory.BAND_MARGIN * survey[0]:
                survey = (area, survey[1], survey[2])
                _check_cut_memory(box, f, lipschitz, survey[2], survey[:2])
        if size == 1:
            break
        size //= 2
        # the children of the kept blocks inside the box, their centres and their parent's value
        blocks, centre, parent_phi = cut_kernels.refine_blocks(blocks, phi, keep, size, cells, box.lower, box.spacing, CUBE_CORNERS)
    # in cell-id order (the search leaves them in block order): the cut's tets then come in id
    # order, so their nodes run through the box layer by layer and the lattice sums over the
    # pieces split into chunks of disjoint node ranges (cutfem.assembly_kernels.scatter_chunks)
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
