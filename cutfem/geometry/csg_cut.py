"""The cut of a background mesh by several level sets: a domain with edges (docs/math.md §16).

A :class:`~cutfem.geometry.csg.Domain` Omega combines the insides {phi_k < 0} of level sets
phi_1..phi_m, each P1 on the background (its nodal interpolant, with the zero rule of
:mod:`cutfem.geometry.nodal_values` applied to each).  A tet on which every phi_k keeps its sign
lies wholly in Omega or wholly outside, as the domain says for that sign pattern, and so does a tet
where the domain does not depend on the level sets that change sign in it (a plane far from the
ball it cuts).  The others are clipped by the planes phi_k = 0 of the level sets that change sign
in them, one after the other
(:mod:`cutfem.geometry.csg_kernels`): each piece of the tet then has one sign pattern, so the
sub-tetrahedra of T ∩ Omega are exact for P1.  The boundary of Omega_h is made of its parts
Gamma_k = {phi_k = 0} ∩ boundary: in each tet, the piece of the plane phi_k = 0 clipped by the
other planes, kept where Omega changes across it, with the outward normal +-grad phi_k / |grad phi_k|
(+ where Omega lies on the side phi_k < 0).  The parts' pieces share their vertices by key across
tets, and the boundary is checked closed: every edge of its triangles is run through as often in
one direction as in the other (two parts meet along an edge; a domain such as
(A ∩ B) ∪ (not A ∩ not B) has edges in four triangles).

:func:`cut_domain` makes the cut (``cut_mesh(background, domain)`` calls it); :class:`CsgCut` has
the sides, element sets, facet sets and measures of a cut by one level set (NEG is Omega, POS the
rest of the box; CUT the tets that carry a piece of the boundary), and ``ds(part, where=...)``: the
boundary, one or several of its parts, and the part of those in a further domain (tagged pieces,
:func:`tagged_pieces`, also for the one-level-set cut's ``ds(where=...)``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from .box import StructuredBox
from .csg import Domain, intersection
from .csg_kernels import clip_tets, clip_triangles, tet_codes
from .cut_kernels import COUNT_FILL_CHUNK
from .keys import pair_up
from .marching import EDGE_I, EDGE_J, FLIP, NVERT
from .markers import CUT, NEG, SIDES, ElementSet, FacetSet, ghost_facets
from .measures import BoundaryPart, ElementVolume, FacetMeasure, SideVolume
from .mesh import TetMesh, triangle_areas
from .nodal_values import CutError, _as_values_function, snapped_nodal_values
from .quadrature import signed_volumes

__all__ = ["CsgCut", "cut_domain", "tagged_pieces"]


@dataclass(eq=False)
class CsgCut:
    """The cut of a background mesh by the level sets of a domain (see the module docstring).

    ``background``, ``domain`` and its ``levelsets`` (m); ``background_values`` (N, m) phi_h of each
    at every node (snapped); ``tet_ids`` (n,) the cut tets (those carrying a piece of the boundary of
    positive area), increasing.  The boundary Gamma_h: ``vertices`` (V, 3), ``triangles`` (T, 3),
    oriented by the outward normal, ``triangle_tets`` (T,) the cut tet of each (0..n-1),
    ``triangle_parts`` (T,) the level set whose zero set holds it, ``triangle_normals`` (T, 3) the
    outward unit normals.  The volume: ``state`` (M,) per background tet 1 (wholly in Omega), 0
    (wholly outside) or -1 (clipped); the clipped tets ``clipped`` (c,) with their sub-tets
    ``sub_tets`` (s, 4, 3), ``sub_inside`` (s,) and ``sub_parent`` (s,) (into ``clipped``)."""

    background: TetMesh
    domain: Domain
    background_values: np.ndarray
    tet_ids: np.ndarray
    vertices: np.ndarray
    triangles: np.ndarray
    triangle_tets: np.ndarray
    triangle_parts: np.ndarray
    triangle_normals: np.ndarray
    state: np.ndarray = field(repr=False)
    clipped: np.ndarray = field(repr=False)
    sub_tets: np.ndarray = field(repr=False)
    sub_inside: np.ndarray = field(repr=False)
    sub_parent: np.ndarray = field(repr=False)
    #: a cut by several level sets is planar: its measures are not deformed (order 1)
    deformation = None
    order = 1

    @property
    def levelsets(self) -> tuple:
        return self.domain.levelsets

    @property
    def h(self) -> float:
        """Global mesh size N**(-1/3) of the background (docs/math.md §2)."""
        return self.background.h

    @property
    def n_tets(self) -> int:
        return len(self.tet_ids)

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    @property
    def values(self) -> np.ndarray:
        """(p, m) phi_h of each level set at the p nodes of the cut tets."""
        return self.background_values[self.elements(CUT).node_ids]

    @cached_property
    def triangle_areas(self) -> np.ndarray:
        return triangle_areas(self.vertices, self.triangles)

    @property
    def area(self) -> float:
        """The area of the boundary Gamma_h."""
        return float(self.triangle_areas.sum())

    def part_area(self, part) -> float:
        """The area of the part of Gamma_h on level set ``part`` (see :meth:`ds`)."""
        return float(self.triangle_areas[self.triangle_parts == self.domain.index(part)].sum())

    # -- element sets, facet sets -----------------------------------------------------------
    @cached_property
    def _element_sets(self) -> dict:
        return {}

    @cached_property
    def _sub_volumes(self) -> np.ndarray:
        return np.abs(signed_volumes(self.sub_tets))

    def _side_of_clipped(self, side) -> np.ndarray:
        """(c,) whether each clipped tet has a part of positive volume on ``side``."""
        sel = self.sub_inside if side == NEG else ~self.sub_inside
        return np.bincount(self.sub_parent[sel], weights=self._sub_volumes[sel], minlength=len(self.clipped)) > 0

    def elements(self, which=CUT):
        """The element set ``NEG`` (the tets with a part of Omega of positive volume, and the cut
        tets), ``POS`` (likewise for the rest of the box) or ``CUT`` (the tets carrying a piece of
        Gamma_h), cached (:class:`~cutfem.geometry.markers.ElementSet`)."""
        if isinstance(which, ElementSet):
            return which
        sets = self._element_sets
        if which not in sets:
            if which == CUT:
                sets[CUT] = ElementSet(self.background, self.tet_ids, name=CUT, cut=self)
            elif which in SIDES:
                mark = self.state == (1 if which == NEG else 0)
                mark[self.clipped[self._side_of_clipped(which)]] = True
                mark[self.tet_ids] = True
                sets[which] = ElementSet(self.background, np.flatnonzero(mark), name=which, cut=self)
            else:
                raise ValueError(f"element sets of a cut are NEG, POS and CUT; got {which!r}")
        return sets[which]

    def interior_facets(self, which=CUT) -> FacetSet:
        """The faces shared by two tets of an element set (default: the cut tets)."""
        return self.elements(which).interior_facets

    def ghost_facets(self, side) -> FacetSet:
        """The ghost-penalty faces of a side: interior faces of its element set with a cut tet
        (:func:`cutfem.geometry.markers.ghost_facets`)."""
        return ghost_facets(self.elements(side), self.tet_ids, side)

    def side_parts(self, side):
        """The cells of ``dx(side)``: ``(whole (w,), sub (s, 4, 3), parent (s,))``, the tets of the
        side's element set that lie wholly in the side and the side's sub-tets of the clipped ones
        (those of positive volume), as :class:`~cutfem.geometry.measures.SideVolume` takes them."""
        es = self.elements(side)
        whole = np.flatnonzero(self.state[es.tet_ids] == (1 if side == NEG else 0))  # local numbers, increasing
        sel = (self.sub_inside if side == NEG else ~self.sub_inside) & (self._sub_volumes > 0)
        parent = self.sub_parent[sel]
        local = np.full(len(self.clipped), -1, dtype=np.int64)
        used = np.zeros(len(self.clipped), dtype=bool)
        used[parent] = True
        local[used] = es.locate(self.clipped[used], "the clipped tets of the side")
        return whole, self.sub_tets[sel], local[parent]

    # -- measures ---------------------------------------------------------------------------
    @cached_property
    def _measures(self) -> dict:
        return {}

    def dx(self, where=NEG):
        """The volume measure of a side (``NEG``: Omega_h, ``POS``: the rest of the box; whole tets and
        sub-tets, :class:`~cutfem.geometry.measures.SideVolume`) or of an element set (whole tets)."""
        key = ("dx", where if isinstance(where, str) else id(where))
        if key not in self._measures:
            if isinstance(where, str) and where in SIDES:
                self._measures[key] = SideVolume(self, where)
            else:
                self._measures[key] = ElementVolume(self.elements(where))
        return self._measures[key]

    def ds(self, part=None, where=None) -> BoundaryPart:
        """The measure on Gamma_h (:class:`~cutfem.geometry.measures.BoundaryPart`, each triangle
        with its outward normal): all of it (``part=None``), or the part on one level set (the level
        set itself, its number 0..m-1 in ``levelsets`` or its name phi1..phim), or on several (a
        list of them).  ``where``: only the pieces in a further domain (a level set's inside, or a
        :class:`~cutfem.geometry.csg.Domain`), clipped exactly (:func:`tagged_pieces`)."""
        if isinstance(part, (list, tuple)) and not part:
            raise ValueError("ds([]) names no part: give a level set of the domain, several in a list, or None for all of Gamma_h")
        parts = None if part is None else tuple(sorted({self.domain.index(p) for p in (part if isinstance(part, (list, tuple)) else [part])}))
        key = ("ds", parts, id(where))
        hit = self._measures.get(key)
        if hit is None or hit[0] is not where:
            sel = slice(None) if parts is None else np.isin(self.triangle_parts, parts)
            points, tets, normals = self.vertices[self.triangles[sel]], self.triangle_tets[sel], self.triangle_normals[sel]
            name = "Gamma_h" if parts is None else "Gamma_h on " + ", ".join(self.domain.names[k] for k in parts)
            if where is not None:
                points, tets, normals = tagged_pieces(self.elements(CUT), points, tets, normals, where)
                name += " where " + _where_text(where)
            hit = self._measures[key] = (where, BoundaryPart(self.elements(CUT), points, tets, normals, name))
        return hit[1]

    def dF(self, facets):
        """The facet measure of a facet set (:class:`~cutfem.geometry.measures.FacetMeasure`)."""
        if not isinstance(facets, FacetSet):
            raise TypeError(f"dF takes a FacetSet (cut.interior_facets(...), cut.ghost_facets(...), or a subset of one), "
                            f"got {type(facets).__name__}")
        key = ("dF", id(facets))
        if key not in self._measures:
            self._measures[key] = FacetMeasure(facets)
        return self._measures[key]

    # -- output -----------------------------------------------------------------------------
    def to_pyvista(self):
        """Gamma_h as a ``pyvista.PolyData`` (cell data: the part and the cut tet of each triangle)."""
        import pyvista as pv

        faces = np.hstack([np.full((self.n_triangles, 1), 3), self.triangles]).ravel()
        poly = pv.PolyData(self.vertices, faces)
        poly.cell_data["part"] = self.triangle_parts
        poly.cell_data["tet"] = self.triangle_tets
        return poly

    def __repr__(self) -> str:
        parts = ", ".join(f"{n} {self.part_area(k):.6g}" for k, n in enumerate(self.domain.names))
        return (f"CsgCut({self.domain}, cut_tets={self.n_tets}, triangles={self.n_triangles}, area={self.area:.6g} "
                f"({parts}), h={self.h:.4g})")


def _where_text(where) -> str:
    return str(where) if isinstance(where, Domain) else f"{where!r} < 0"


def _nodal_values(background, levelset, name: str) -> np.ndarray:
    """The snapped nodal values of one level set of a domain; its errors name it."""
    try:
        return snapped_nodal_values(background, levelset)
    except (ValueError, TypeError) as exc:
        raise type(exc)(f"level set {name} of the domain ({levelset!r}): {exc}") from None


def cut_domain(background: TetMesh, domain: Domain, check_boundary: bool = True) -> CsgCut:
    """Cut ``background`` by the level sets of ``domain`` (see the module docstring).

    Raises :class:`~cutfem.geometry.nodal_values.CutError` when a level set does not change sign in
    the mesh (its zero set misses the box), when Omega reaches the boundary of the mesh (unless
    ``check_boundary=False``), when Omega_h is empty or has no boundary inside the mesh, or when
    Gamma_h is not closed (an edge run through more often one way than the other); ValueError for
    NaN or infinite values, naming the level set."""
    if not isinstance(domain, Domain):
        raise TypeError(f"cut_domain takes a Domain (cutfem.intersection, union, difference, complement), got {type(domain).__name__}")
    levelsets, names, m = domain.levelsets, domain.names, len(domain.levelsets)
    table = domain.table()
    values = np.stack([_nodal_values(background, s, n) for s, n in zip(levelsets, names)])  # (m, N)
    counts = np.stack([background.tet_node_counts(values[k] < 0) for k in range(m)])  # (m, M): the level sets, not the tets
    fixed, mixed = np.empty(background.n_tets, dtype=np.int32), np.empty(background.n_tets, dtype=np.int32)
    state = np.empty(background.n_tets, dtype=np.int8)
    tet_codes(counts, table, fixed, mixed, state)
    del counts
    changes = int(np.bitwise_or.reduce(mixed)) if len(mixed) else 0
    for k in range(m):
        if not (changes >> k) & 1:
            lo, hi = background.bounds
            sign = "negative" if np.nanmax(values[k]) < 0 else ">= 0"
            raise CutError(f"level set {names[k]} of the domain ({levelsets[k]!r}) does not cut the background mesh: it is {sign} "
                           f"at every node of the box [{np.round(lo, 6).tolist()}, {np.round(hi, 6).tolist()}], so its zero "
                           "set misses the box and Omega does not depend on it. Move it into the box, or leave it out "
                           "of the domain.")
    if check_boundary:
        _check_domain_boundary(background, values, table, domain)
    clipped = np.flatnonzero(mixed)
    structured = isinstance(background, StructuredBox)
    nodes = background.kuhn_tet_nodes(clipped) if structured else background.tets[clipped]
    x = background.node_coordinates(nodes) if structured else background.points[nodes]
    phi = np.moveaxis(values[:, nodes], 0, -1)  # (c, 4, m)
    whole, sub_x, sub_in, sub_tet, tri_x, tri_key, tri_part, tri_normal, tri_tet = clip_tets(
        x, phi, nodes, fixed[clipped], mixed[clipped], table, EDGE_I, EDGE_J, NVERT, FLIP, COUNT_FILL_CHUNK)
    del x, phi, fixed, mixed
    state[clipped] = whole
    # the boundary's vertices by key: one vertex per key, from its first slot
    order, starts, counts = pair_up(tuple(tri_key.reshape(-1, tri_key.shape[-1]).T))
    ids = np.empty(len(order), dtype=np.int64)
    ids[order] = np.repeat(np.arange(len(starts)), counts)
    vertices = tri_x.reshape(-1, 3)[order[starts]]
    triangles = ids.reshape(-1, 3)
    # a triangle with a vertex twice (a piece collapsed on a plane through nodes or edges) has no
    # area and no boundary: left out; the others must close up
    proper = (triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2]) & (triangles[:, 2] != triangles[:, 0])
    _check_closed_boundary(vertices, triangles[proper], background, check_boundary, domain)
    areas = triangle_areas(vertices, triangles)
    keep = proper & (areas > 0)  # pieces flattened by the zero rule carry nothing
    if not keep.any():
        raise CutError(f"the domain {domain} has no boundary inside the background mesh: Omega_h is empty (the insides of its "
                       "level sets do not meet as the domain combines them) or fills the whole box. Check the signs of the "
                       "level sets (negative inside) and the domain's expression.")
    triangles, tri_part, tri_normal, tri_cand = triangles[keep], tri_part[keep], tri_normal[keep], tri_tet[keep]
    first = np.ones(len(tri_cand), dtype=bool)  # the triangles come in tet order: the cut tets by their first
    first[1:] = tri_cand[1:] != tri_cand[:-1]
    tet_ids = clipped[tri_cand[first]]
    return CsgCut(background=background, domain=domain, background_values=np.ascontiguousarray(values.T), tet_ids=tet_ids,
                  vertices=vertices, triangles=triangles, triangle_tets=np.cumsum(first) - 1,
                  triangle_parts=tri_part, triangle_normals=tri_normal, state=state, clipped=clipped, sub_tets=sub_x,
                  sub_inside=sub_in, sub_parent=sub_tet)


def _check_domain_boundary(background, values, table, domain) -> None:
    """Omega must stay inside the mesh: no boundary node of the background in Omega (by its signs)."""
    b = background.boundary_nodes
    code = np.zeros(len(b), dtype=np.int64)
    for k in range(len(values)):
        code |= (values[k, b] < 0).astype(np.int64) << k
    inside = table[code]
    if inside.any():
        lo, hi = background.bounds
        x = background.node_coordinates(b[inside][:1])[0] if isinstance(background, StructuredBox) else background.points[b[inside][0]]
        raise CutError(f"{int(inside.sum())} boundary nodes of the background mesh lie in the domain {domain} (first at "
                       f"{np.round(x, 6).tolist()}): Omega reaches or leaves the box [{np.round(lo, 6).tolist()}, "
                       f"{np.round(hi, 6).tolist()}]. Enlarge the box so that it contains Omega with a cell to spare, bound "
                       "Omega by further level sets (a box of planes), or check the signs of the level sets (negative inside).")


def _check_closed_boundary(vertices, triangles, background, check_boundary: bool, domain) -> None:
    """Raise CutError unless every edge of the boundary's triangles is run through as often in one
    direction as in the other (Gamma_h is closed; with ``check_boundary=False`` it may end on the
    faces of the box)."""
    t = triangles.astype(np.int64)
    a, b = t.reshape(-1), np.roll(t, -1, axis=1).reshape(-1)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    order, starts, _ = pair_up((lo, hi))
    turns = np.add.reduceat(np.sign(b - a)[order], starts) if len(order) else np.zeros(0, dtype=np.int64)
    open_ = turns != 0
    if not open_.any():
        return
    edges = np.stack([lo[order[starts]], hi[order[starts]]], axis=1)
    if not check_boundary:
        box_lo, box_hi = (np.asarray(v, float) for v in background.bounds)
        eps = 1e-9 * float(np.linalg.norm(box_hi - box_lo))
        x = vertices[edges[open_]]
        on_face = np.any((np.abs(x - box_lo) <= eps) | (np.abs(x - box_hi) <= eps), axis=2).all(axis=1)
        open_[np.flatnonzero(open_)[on_face]] = False
        if not open_.any():
            return
    where = vertices[edges[open_][0]].mean(axis=0)
    raise CutError(f"the boundary of the domain {domain} is not closed: {int(open_.sum())} edges of its triangles are run "
                   f"through more often in one direction than in the other (first near {np.round(where, 6).tolist()}). Likely "
                   "cause: level sets that meet in degenerate ways within one cell (refine the background mesh or move "
                   "a level set slightly).")


def _snapped_at(elements: ElementSet, f) -> np.ndarray:
    """A function's values at the nodes of an element set, with the zero rule's snap: values of
    modulus at most 1e-12 times the largest over the node's tets set to 0."""
    v = np.asarray(f(elements.points), dtype=float).reshape(-1)
    if not np.isfinite(v).all():
        raise ValueError(f"the level set of where= gave {int(np.sum(~np.isfinite(v)))} NaN or infinite values at the nodes of "
                         "the cut tets; check that it is defined around the boundary")
    scale = np.abs(v)
    local = scale.copy()
    np.maximum.at(local, elements.tets.reshape(-1), np.repeat(scale[elements.tets].max(axis=1), 4))
    v[scale <= 1e-12 * local] = 0.0
    return v


def tagged_pieces(elements: ElementSet, points, tets, normals, where):
    """The triangles ``points`` (T, 3, 3) in the tets ``tets`` (T,) of ``elements`` (their normals
    ``normals`` (T, 3)) clipped by the P1 interpolants of the level sets of ``where`` (a level set,
    whose inside {psi < 0} is kept, or a :class:`~cutfem.geometry.csg.Domain`), keeping the pieces
    in that domain: ``(points (T', 3, 3), tets (T',), normals (T', 3))``, each triangle's orientation
    kept.  Exact for P1: the interpolants are linear on each tet.  Values exactly 0 count as outside
    (the zero rule)."""
    domain = where if isinstance(where, Domain) else intersection(where)
    vals = []
    for s in domain.levelsets:
        if isinstance(s, np.ndarray):  # nodal values of the background
            v = np.asarray(s, dtype=float).reshape(-1)
            if v.size != elements.background.n_points:
                raise ValueError(f"where= got {v.size} nodal values for a background of {elements.background.n_points} nodes")
            vals.append(_snapped_at(elements, lambda x, v=v: v[elements.node_ids]))
        else:
            vals.append(_snapped_at(elements, _as_values_function(s)))
    node_values = np.stack(vals, axis=1)  # (p, mw)
    points = np.asarray(points, dtype=float).reshape(-1, 3, 3)
    tets = np.asarray(tets, dtype=np.int64)
    # psi at the triangles' vertices: lambda_k(x) = delta_k0 + grad lambda_k . (x - x_0) in the tet
    G = elements.gradients_of(tets)  # (T, 4, 3)
    x0 = elements.points[elements.tets[tets, 0]]
    lam = np.einsum("tkd,tvd->tvk", G, points - x0[:, None, :])
    lam[:, :, 0] += 1.0
    psi = np.einsum("tvk,tkj->tvj", lam, node_values[elements.tets[tets]])
    out, source = clip_triangles(points, psi, domain.table(), COUNT_FILL_CHUNK)
    return out, tets[source], np.asarray(normals, dtype=float)[source]
