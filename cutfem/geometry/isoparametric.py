"""The isoparametric cut geometry: a P2 deformation Theta_h that lifts the planar cut to third order
(docs/math.md §17; Lehrenfeld, CMAME 300, 2016).

The cut stays the one of the P1 interpolant phi_h1 (its pieces, sub-tets and zero rule are those of
:mod:`cutfem.geometry.cut`); what changes is the map from those cells to the integration domain.

Theta_h
-------
phi_h2 is the P2 interpolant of the level set on the cut tets: the snapped nodal values of phi_h1
at the vertices (so phi_h2 = phi_h1 there) and phi itself at the edge midpoints.  For every P2 node
y of a cut tet T the search direction G(y) is grad phi_h2 at y averaged over the cut tets that have
y, and the shift d_T(y) solves, with T's polynomial phi_h2|T continued beyond T,

    phi_h2|T (y + d G(y)) = phi_h1(y),

a quadratic equation in d solved by Newton steps from d = 0 (all nodes at once).  The shift of y is
d(y) G(y), d(y) the mean of d_T(y) over the cut tets that have y; nodes of no cut tet do not move.
At a vertex phi_h2 = phi_h1, so d = 0: only edge midpoints move, by O(h^2).  Then

    Theta_h(x) = x + sum_a N_a(x) d(y_a) G(y_a)        (N_a the P2 Lagrange basis of the tet of x),

continuous (the shift of a node is one value for every tet that has it) and the identity on every
tet none of whose P2 nodes moved: only the cut tets and the tets that share an edge with one are
deformed.  Theta_h({phi_h1 = 0}) approximates the surface to O(h^3).

Deformed measures
-----------------
A cut made with ``cut_mesh(background, levelset, order=2)`` carries its :class:`Deformation`, and its
measures ``dx(NEG)``, ``dx(POS)``, ``dx(elements)``, ``ds()`` and ``ds(where=...)`` give quadratures
on the deformed cells: from the rule's points x^ on the planar cells,

    points = Theta_h(x^),  weights = w^ |det D Theta_h(x^)|                       (volumes),
    weights = w^ |cof(D Theta_h) n_h|,  normal = cof(D Theta_h) n_h / |...|        (surfaces),

cof(J) = det(J) J^-T, per point, with ``reference_points`` x^ (where fields evaluate their basis)
and ``jacobians`` D Theta_h(x^) (fields' gradients map by D Theta_h^-T).  Cells on which Theta_h is
the identity keep their points and weights (identity Jacobians where a quadrature mixes both, and no
``reference_points`` at all when none of its cells moved).  A part ``ds(where=psi)`` of S_h is the
planar clip of the pieces by psi_h mapped by Theta_h: its dividing line moves with the surface, not
along psi = 0, so a part's area is O(h^2) accurate while the parts still sum to the whole.  The
facet measures ``dF`` (the ghost penalty's faces, J_F) stay on the undeformed faces: a penalty on the
planar faces of the background mesh keeps its purpose (it controls the extension of the fields into
the active tets), and the deformed faces would change it by a relative O(h) only
(D Theta_h - I = O(h)).  The built-in terms' closed P1 forms hold on planar cells, so on a deformed
measure :func:`cutfem.fem.forms.assemble` integrates their integrands by quadrature.
"""

from __future__ import annotations

import numpy as np

from . import isoparametric_kernels
from .keys import unique_keys
from .markers import CUT, same_background
from .mesh import barycentric_gradients
from .nodal_values import CutError, _as_values_function
from .quadrature import Quadrature

__all__ = ["Deformation", "P2_PAIRS", "quadratic_form"]

#: the P2 nodes of a tet as pairs of its vertices: the vertices (a, a), then the edge midpoints
P2_PAIRS = np.array([[0, 0], [1, 1], [2, 2], [3, 3], [0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
#: (10, 4) barycentric coordinates of the P2 nodes
P2_BARY = 0.5 * (np.eye(4)[P2_PAIRS[:, 0]] + np.eye(4)[P2_PAIRS[:, 1]])

#: Newton steps for the shifts: the equation is quadratic in d and d = O(h^2), so three or four do
NEWTON_STEPS = 12


def quadratic_form(nodal: np.ndarray) -> np.ndarray:
    """(m, 4, 4, ...) the symmetric Q with ``sum_a N_a(lam) v_a = lam^T Q lam`` for every lam with
    sum(lam) = 1, for P2 nodal values ``v`` (m, 10, ...) in the order of :data:`P2_PAIRS`.

    From lam_i (2 lam_i - 1) = lam_i^2 - sum_{j != i} lam_i lam_j on sum(lam) = 1: Q_ii = v_i and
    Q_ij = 2 v_ij - (v_i + v_j) / 2.  Then the P2 function is lam^T Q lam and its gradient
    2 sum_l (Q lam)_l grad lam_l (the derivatives along sum(lam) = 1 agree), all by small products."""
    nodal = np.asarray(nodal, dtype=float)
    q = np.empty(nodal.shape[:1] + (4, 4) + nodal.shape[2:])
    vertex = nodal[:, :4]
    for a in range(4):
        q[:, a, a] = vertex[:, a]
    for e, (i, j) in enumerate(P2_PAIRS[4:]):
        q[:, i, j] = q[:, j, i] = 2.0 * nodal[:, 4 + e] - 0.5 * (vertex[:, i] + vertex[:, j])
    return q


def _pair_keys(node_ids: np.ndarray, n: int) -> np.ndarray:
    """(m, 10) the key lo * n + hi of each P2 node of tets with node ids ``node_ids`` (m, 4) below n:
    the pair of vertex ids it lies between (a vertex is the pair (a, a))."""
    a = node_ids[:, P2_PAIRS[:, 0]].astype(np.int64)
    b = node_ids[:, P2_PAIRS[:, 1]].astype(np.int64)
    return np.minimum(a, b) * n + np.maximum(a, b)


class Deformation:
    """Theta_h of a cut by one level set (module docstring): the shifts of the P2 nodes of its cut
    tets, and Theta_h, D Theta_h and the deformed quadratures on any element set of the same
    background.

    ``cut``: a :class:`cutfem.geometry.cut.CutMesh` of a level set given as a function (its
    ``levelset``: a LevelSet or a callable; an array of nodal values has no values at the edge
    midpoints), as ``cut_mesh(..., order=2)`` makes it.  Raises :class:`~cutfem.geometry.nodal_values.CutError` when a
    shift cannot be found (the line y + d G misses the zero set of phi_h2 near y: the mesh is too
    coarse for the level set).

    Attributes: ``node_keys`` (K,) sorted keys ``lo * N + hi`` of the P2 nodes of the cut tets in
    background node ids (N background nodes; a vertex is (a, a)), ``shifts`` (K, 3) their shifts
    d G, ``directions`` (K, 3) the averaged gradients G.
    """

    order = 2

    def __init__(self, cut):
        value = _as_values_function(cut.levelset)
        n_bg = int(cut.background.n_points)
        tets = np.asarray(cut.tets, dtype=np.int64)
        points, p = cut.points, len(cut.points)
        local = _pair_keys(tets, p)  # (n, 10) in the active numbering
        keys, inverse = unique_keys(local.reshape(-1), return_inverse=True)
        inverse = inverse.reshape(local.shape)
        lo, hi = keys // p, keys % p
        # phi_h2 at its nodes: phi_h1's snapped values at the vertices, phi at the edge midpoints
        nodal = np.asarray(cut.values, dtype=float)[lo]
        mid = np.flatnonzero(lo != hi)
        at_mid = np.asarray(value(0.5 * (points[lo[mid]] + points[hi[mid]])), dtype=float)
        if at_mid.shape != mid.shape or not np.all(np.isfinite(at_mid)):
            raise ValueError("the level set gave values that are not finite (or of the wrong shape) at the edge "
                             "midpoints of the cut tets; order=2 evaluates it there")
        nodal[mid] = at_mid
        form = quadratic_form(nodal[inverse])  # (n, 4, 4): phi_h2 on each cut tet is lam^T form lam
        grads = np.asarray(cut.basis_gradients, dtype=float)  # (n, 4, 3)
        # grad phi_h2|T = 2 (form lam) . grad lam at its own nodes, averaged over the cut tets of each node
        at_nodes = 2.0 * np.einsum("nlj,kj,nld->nkd", form, P2_BARY, grads)
        count = np.bincount(inverse.reshape(-1), minlength=len(keys)).astype(float)
        direction = np.stack([np.bincount(inverse.reshape(-1), weights=at_nodes[..., c].reshape(-1), minlength=len(keys))
                              for c in range(3)], axis=1) / count[:, None]
        step = _newton_shifts(form, grads, direction[inverse], cut.values[tets], cut.elements(CUT).h)
        d = np.bincount(inverse.reshape(-1), weights=step.reshape(-1), minlength=len(keys)) / count
        node_ids = np.asarray(cut.node_ids, dtype=np.int64)
        # increasing keys: node_ids increase with the active numbers
        self._set(cut.background, node_ids[lo] * n_bg + node_ids[hi], direction, d[:, None] * direction)

    def _set(self, background, node_keys, directions, shifts) -> None:
        """Hold the P2 nodes' keys (increasing, in ``background``'s node ids) with their directions
        and shifts, and the moved ones for :meth:`element_shifts`."""
        self.background, self._n = background, int(background.n_points)
        self.node_keys, self.directions, self.shifts = node_keys, directions, shifts
        moved = np.any(shifts != 0.0, axis=1)
        self._moved_keys, self._moved_shifts = node_keys[moved], shifts[moved]
        self._moved_vertices = np.unique(np.concatenate([node_keys[moved] // self._n, node_keys[moved] % self._n]))
        self._element_cache: dict = {}

    def on(self, background, ids) -> "Deformation":
        """The same Theta_h on another background mesh whose node i is node ``ids[i]`` of this one's
        (a part of it): the P2 nodes with both ends among ``ids``.  A distributed run computes the
        shifts on a slab one cell layer wider than the cells it assembles, so that each node's means
        over its cut tets are the serial ones (docs/math.md §19), and moves them onto its slabs."""
        ids = np.asarray(ids, dtype=np.int64)
        local = np.full(self._n, -1, dtype=np.int64)
        local[ids] = np.arange(len(ids))
        a, b = local[self.node_keys // self._n], local[self.node_keys % self._n]
        keep = np.flatnonzero((a >= 0) & (b >= 0))
        n = int(background.n_points)
        keys = np.minimum(a[keep], b[keep]) * n + np.maximum(a[keep], b[keep])
        order = np.argsort(keys, kind="stable")
        out = object.__new__(Deformation)
        out._set(background, keys[order], self.directions[keep[order]], self.shifts[keep[order]])
        return out

    def __repr__(self) -> str:
        return f"Deformation(order=2, nodes={len(self.node_keys)}, moved={len(self._moved_keys)})"

    @property
    def max_shift(self) -> float:
        """The largest |shift| of a P2 node (O(h^2) for a smooth level set)."""
        return float(np.max(np.linalg.norm(self.shifts, axis=1))) if len(self.shifts) else 0.0

    # -- Theta_h on an element set ----------------------------------------------------------------
    def element_shifts(self, elements):
        """``(rows (m,), shifts (r, 10, 3))`` of an element set of the same background: the shifts of
        the P2 nodes of each tet that has a moved node, at row ``rows[e]``, and ``rows[e] = -1`` on
        the tets where Theta_h is the identity (cached per set)."""
        hit = self._element_cache.get(id(elements))
        if hit is not None and hit[0] is elements:
            return hit[1]
        if not same_background(elements.background, self.background):
            raise ValueError(f"{elements!r} lies on another background mesh than the cut this deformation lifts")
        rows = np.full(elements.n_elements, -1, dtype=np.int64)
        shifts = np.zeros((0, 10, 3))
        if len(self._moved_keys):
            tets = np.asarray(elements.tets)
            near = np.isin(np.asarray(elements.node_ids), self._moved_vertices)  # only tets with such a vertex can move
            candidates = np.flatnonzero(near[tets].any(axis=1))
            keys = _pair_keys(np.asarray(elements.node_ids, dtype=np.int64)[tets[candidates]], self._n)
            where = np.minimum(np.searchsorted(self._moved_keys, keys), len(self._moved_keys) - 1)
            found = self._moved_keys[where] == keys
            moved = found.any(axis=1)
            shifts = np.where(found[moved][..., None], self._moved_shifts[where[moved]], 0.0)
            rows[candidates[moved]] = np.arange(len(shifts))
        self._element_cache[id(elements)] = (elements, (rows, shifts))
        return rows, shifts

    def map(self, elements, cells, points):
        """``(Theta_h(x), D Theta_h(x))`` at points x (m, q, 3) of the tets ``cells`` (m,) (local indices
        of ``elements``): (m, q, 3) and (m, q, 3, 3), rows the components of Theta_h.  The points
        may lie anywhere in their tets (the P2 polynomial of each tet is evaluated)."""
        rows, shifts = self.element_shifts(elements)
        cells = np.asarray(cells, dtype=np.int64)
        points = np.asarray(points, dtype=float)
        theta = points.copy()
        jac = np.zeros(points.shape + (3,))
        jac[...] = np.eye(3)
        moving = np.flatnonzero(rows[cells] >= 0)
        if len(moving):
            vertices = elements.points[np.asarray(elements.tets)[cells[moving]]]
            theta[moving], jac[moving] = _p2_map(vertices, shifts[rows[cells[moving]]], points[moving])
        return theta, jac

    def hessians(self, elements, cells) -> np.ndarray:
        """(m, 3, 3, 3) the Hessians of the components of Theta_h (component first) on the tets
        ``cells`` (local indices of ``elements``): constant on each tet, 2 G^T Q_c G with Q_c the
        quadratic form of component c's shifts (:func:`quadratic_form`) and G the barycentric
        gradients; zero where Theta_h is the identity."""
        rows, shifts = self.element_shifts(elements)
        cells = np.asarray(cells, dtype=np.int64)
        out = np.zeros((len(cells), 3, 3, 3))
        moving = np.flatnonzero(rows[cells] >= 0)
        if len(moving):
            grads, _ = barycentric_gradients(elements.points[np.asarray(elements.tets)[cells[moving]]])
            Q = np.moveaxis(quadratic_form(shifts[rows[cells[moving]]]), 3, 1)  # (m, c, 4, 4)
            out[moving] = 2.0 * np.matmul(np.matmul(np.swapaxes(grads, 1, 2)[:, None], Q), grads[:, None])
        return out

    def deform(self, quad: Quadrature, elements, surface: bool) -> Quadrature:
        """The quadrature ``quad`` of cells in ``elements`` (its ``parent`` indexes them) mapped by
        Theta_h (module docstring): ``quad`` itself when none of its cells moves."""
        rows, _ = self.element_shifts(elements)
        if not np.any(rows[quad.parent] >= 0):
            return quad
        points, jac = self.map(elements, quad.parent, quad.points)
        det = np.empty(quad.weights.shape)
        factor, normal, n = (np.empty(det.shape), np.empty(quad.points.shape), quad.point_normals) if surface else \
            (det, np.empty((0, 1, 3)), np.empty((0, 1, 3)))
        isoparametric_kernels.deformed_measure(jac, np.ascontiguousarray(n, dtype=float), det, factor, normal)
        if not np.all(det > 0.0):
            bad = np.flatnonzero(~np.all(det > 0.0, axis=1))[0]
            raise CutError(f"the isoparametric map Theta_h folds (det D Theta_h = {float(det[bad].min()):.3g} <= 0 in a cell "
                           f"of element {int(quad.parent[bad])}): the mesh is too coarse for the curvature of the level set; "
                           "refine the background mesh")
        return Quadrature(points, quad.weights * factor, quad.parent, normal if surface else None, quad.bary, quad.whole,
                          reference_points=quad.points, jacobians=jac)


def _p2_map(vertices: np.ndarray, shifts: np.ndarray, points: np.ndarray):
    """Theta_h (m, q, 3) and D Theta_h (m, q, 3, 3) at ``points`` of tets ``vertices`` (m, 4, 3) whose P2
    nodes have ``shifts`` (m, 10, 3): x + lam^T Q lam and I + 2 (Q lam) grad lam (:func:`quadratic_form`),
    point by point (:func:`~cutfem.geometry.isoparametric_kernels.p2_map`)."""
    grads, _ = barycentric_gradients(vertices)
    theta, jac = np.empty(points.shape), np.empty(points.shape + (3,))
    isoparametric_kernels.p2_map(np.ascontiguousarray(vertices, dtype=float), np.ascontiguousarray(grads, dtype=float),
                                 np.ascontiguousarray(shifts, dtype=float), np.ascontiguousarray(points, dtype=float), theta, jac)
    return theta, jac


def _newton_shifts(form, grads, direction, p1_values, h):
    """(n, 10) the shifts d_T with phi_h2|T(y + d G) = phi_h1(y) at the P2 nodes y of each cut tet T.

    ``form`` (n, 4, 4) phi_h2 on each tet (:func:`quadratic_form`), ``grads`` (n, 4, 3) its
    barycentric gradients, ``direction`` (n, 10, 3) G at its nodes, ``p1_values`` (n, 4) phi_h1 at its
    vertices, ``h`` (n,) its size.  Along the line the barycentric coordinates are
    lam(d) = lam_y + d r, r = grad(lam) . G (sum(r) = 0), so the equation is the quadratic
    a d^2 + b d + c = 0 with a = r^T Q r, b = 2 lam_y^T Q r, c = lam_y^T Q lam_y - phi_h1(y); Newton from
    d = 0 converges in a few steps when d = O(h^2) (done when the last step moved the point by at most
    1e-12 h)."""
    target = p1_values @ P2_BARY.T  # (n, 10): phi_h1 at the nodes
    rate = np.einsum("nld,nkd->nkl", grads, direction)  # r
    length = np.linalg.norm(direction, axis=-1)
    if not np.all(length > 0.0):
        raise CutError("grad phi_h2 vanishes at a P2 node of a cut tet, so the isoparametric shift has no direction: "
                       "the level set is flat (or has a critical point) at its zero set; use a level set with a nonzero "
                       "gradient there, or refine the background mesh")
    qr = np.einsum("nlj,nkj->nkl", form, rate)
    a = np.einsum("nkl,nkl->nk", rate, qr)
    b = 2.0 * np.einsum("kl,nkl->nk", P2_BARY, qr)
    c = np.einsum("kl,nlj,kj->nk", P2_BARY, form, P2_BARY) - target
    d = np.zeros(target.shape)
    done = False
    for _ in range(NEWTON_STEPS):
        with np.errstate(divide="ignore", invalid="ignore"):
            step = ((a * d + b) * d + c) / (2.0 * a * d + b)
        if not np.all(np.isfinite(step)):
            break
        d -= step
        if np.all(np.abs(step) * length <= 1e-12 * h[:, None]):
            done = True
            break
    if not (done and np.all(np.abs(d) * length <= h[:, None])):
        raise CutError("the isoparametric shifts of some P2 nodes did not converge (the line from the node along grad "
                       "phi_h2 does not meet {phi_h2 = phi_h1} within the tet's size): the background mesh is too coarse "
                       "for the level set; refine it")
    return d
