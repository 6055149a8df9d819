"""Forms: bilinear and linear forms written as vectorized integrands, and the stabilizations.

Writing a form
--------------
A form is a plain function of arrays shaped (elements x quadrature points)::

    from cutfem.forms import bilinear_form, dot

    @bilinear_form(symmetric=True)
    def helmholtz(u, v, w):
        return dot(u.tgrad, v.tgrad) - w.k2 * u * v     # w carries x, n, h and any extra data

    A = helmholtz.assemble(space, k2=4.0)

``u`` and ``v`` are :class:`BasisField` objects: ``u.value`` (m, q), ``u.grad`` and ``u.tgrad``
(m, 1, 3) (the full gradient and the tangential gradient ``P_h grad``; P1 gradients are constant on
an element), and arithmetic on a BasisField acts on its value.  ``w`` is a :class:`QuadData` with
``w.x`` (m, q, 3), ``w.n`` (m, 1, 3) (the element normal n_h), ``w.h`` and the keyword arguments given
to ``assemble``.  The integrand returns an array broadcastable to (m, q).  Assembly loops only over
the k x k local basis pairs (k = 3 or 4), never over elements; ``symmetric=True`` evaluates i <= j
and mirrors, so the matrix is exactly symmetric.

Built-in forms (SPEC §3-4): :func:`mass`, :func:`tangential_stiffness`, :func:`load`, :func:`position_load`,
:func:`edge_jump_penalty` (J_E), :func:`face_jump_penalty` (J_F), :func:`normal_gradient_penalty`,
:func:`volume_mass`, :func:`volume_stiffness`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from .assembly import assemble_vector, gram
from .mesh import cross, vertex_columns
from .spaces import CutP1Space, SurfaceP1Space

__all__ = [
    "BasisField",
    "QuadData",
    "BilinearForm",
    "LinearForm",
    "bilinear_form",
    "linear_form",
    "dot",
    "mass",
    "tangential_stiffness",
    "load",
    "position_load",
    "edge_jump_penalty",
    "face_jump_penalty",
    "normal_gradient_penalty",
    "volume_mass",
    "volume_stiffness",
]


def dot(a, b):
    """Dot product over the last axis."""
    return np.einsum("...d,...d->...", a, b)


class BasisField:
    """A basis function (or its values) at quadrature points; arithmetic acts on ``value``."""

    __slots__ = ("value", "grad", "tgrad")

    def __init__(self, value, grad, tgrad):
        self.value, self.grad, self.tgrad = value, grad, tgrad

    def __array__(self, dtype=None, copy=None):
        return np.asarray(self.value, dtype=dtype)

    def __mul__(self, other):
        return self.value * (other.value if isinstance(other, BasisField) else other)

    __rmul__ = __mul__

    def __add__(self, other):
        return self.value + (other.value if isinstance(other, BasisField) else other)

    __radd__ = __add__

    def __sub__(self, other):
        return self.value - (other.value if isinstance(other, BasisField) else other)

    def __rsub__(self, other):
        return other - self.value

    def __truediv__(self, other):
        return self.value / (other.value if isinstance(other, BasisField) else other)

    def __rtruediv__(self, other):
        return other / self.value

    def __pow__(self, power):
        return self.value**power

    def __neg__(self):
        return -self.value


@dataclass
class QuadData:
    """Quadrature data handed to an integrand: points ``x`` (m, q, 3), element normals ``n``
    (m, 1, 3) or None, mesh size ``h``, parent element ids, and user parameters as attributes."""

    x: np.ndarray
    n: np.ndarray | None
    h: float
    parent: np.ndarray
    params: dict = field(default_factory=dict)

    def __getattr__(self, name):
        params = self.__dict__.get("params", {})
        if name in params:
            return params[name]
        raise AttributeError(f"quadrature data has no field {name!r}; pass it as a keyword to assemble()")


def _element_data(space, measure, degree):
    quad = space.quadrature(measure, degree)
    parent = quad.parent
    G = space.element_gradients[parent]  # (m, k, 3)
    normals = getattr(space, "element_normals", None)
    if normals is not None and measure != "volume":
        n = normals[parent]
        tG = G - np.einsum("mkd,md->mk", G, n)[..., None] * n[:, None, :]
        n = n[:, None, :]
    else:
        n, tG = None, G
    return quad, G, tG, n


def _reduce_to_elements(space, blocks, parent):
    """Sum per-quadrature-cell blocks into per-element blocks (cells of one element contiguous or not)."""
    n_el = len(space.element_dofs)
    if len(parent) == n_el and np.array_equal(parent, np.arange(n_el)):
        return blocks
    order = np.argsort(parent, kind="stable")
    p = parent[order]
    starts = np.flatnonzero(np.r_[True, p[1:] != p[:-1]])
    out = np.zeros((n_el,) + blocks.shape[1:])
    out[p[starts]] = np.add.reduceat(blocks[order], starts, axis=0)
    return out


class BilinearForm:
    """A bilinear form a(u, v) = sum over quadrature of integrand(u, v, w) * weight."""

    def __init__(self, integrand, symmetric=False, measure="surface", degree=2):
        self.integrand = integrand
        self.symmetric = symmetric
        self.measure = measure
        self.degree = degree
        self.__doc__ = integrand.__doc__
        self.__name__ = getattr(integrand, "__name__", "form")

    def blocks(self, space, measure=None, degree=None, **params):
        """Local element blocks (n_elements, k, k)."""
        measure = measure or self.measure
        degree = self.degree if degree is None else degree
        quad, G, tG, n = _element_data(space, measure, degree)
        phi = space.basis_values(quad)
        w = QuadData(x=quad.points, n=n, h=space.h, parent=quad.parent, params=params)
        m, k = G.shape[0], G.shape[1]
        fields = [BasisField(phi[..., a], G[:, None, a], tG[:, None, a]) for a in range(k)]
        blocks = np.empty((m, k, k))
        for i in range(k):
            for j in range(i if self.symmetric else 0, k):
                val = np.broadcast_to(np.asarray(self.integrand(fields[j], fields[i], w), dtype=float), quad.weights.shape)
                blocks[:, i, j] = np.einsum("mq,mq->m", val, quad.weights)
                if self.symmetric:
                    blocks[:, j, i] = blocks[:, i, j]
        return _reduce_to_elements(space, blocks, quad.parent)

    def assemble(self, space, measure=None, degree=None, **params) -> sp.csr_matrix:
        """The n_dofs x n_dofs CSR matrix of the form on ``space``."""
        return space.pattern("elements").matrix(self.blocks(space, measure, degree, **params))

    __call__ = assemble


class LinearForm:
    """A linear form l(v) = sum over quadrature of integrand(v, w) * weight; the integrand may return
    (m, q) or (m, q, c) for c components at once."""

    def __init__(self, integrand, measure="surface", degree=4):
        self.integrand = integrand
        self.measure = measure
        self.degree = degree
        self.__doc__ = integrand.__doc__

    def assemble(self, space, measure=None, degree=None, **params) -> np.ndarray:
        measure = measure or self.measure
        degree = self.degree if degree is None else degree
        quad, G, tG, n = _element_data(space, measure, degree)
        phi = space.basis_values(quad)
        w = QuadData(x=quad.points, n=n, h=space.h, parent=quad.parent, params=params)
        k = G.shape[1]
        local = []
        for a in range(k):
            val = np.asarray(self.integrand(BasisField(phi[..., a], G[:, None, a], tG[:, None, a]), w), dtype=float)
            if val.ndim == 3:
                local.append(np.einsum("mqc,mq->mc", val, quad.weights))
            else:
                local.append(np.einsum("mq,mq->m", np.broadcast_to(val, quad.weights.shape), quad.weights))
        local = np.stack(local, axis=1)  # (m, k) or (m, k, c)
        return assemble_vector(space.element_dofs[quad.parent], local, space.n_dofs)

    __call__ = assemble


def bilinear_form(integrand=None, *, symmetric=False, measure="surface", degree=2):
    """Decorator turning ``integrand(u, v, w)`` into a :class:`BilinearForm`."""
    if integrand is None:
        return lambda f: BilinearForm(f, symmetric=symmetric, measure=measure, degree=degree)
    return BilinearForm(integrand, symmetric=symmetric, measure=measure, degree=degree)


def linear_form(integrand=None, *, measure="surface", degree=4):
    """Decorator turning ``integrand(v, w)`` into a :class:`LinearForm`."""
    if integrand is None:
        return lambda f: LinearForm(f, measure=measure, degree=degree)
    return LinearForm(integrand, measure=measure, degree=degree)


# ---------------------------------------------------------------------------------------------
# built-in forms
#
# The built-in symmetric forms are sums of squares, so each is assembled as a Gram matrix E^T E
# (cutfem.assembly.gram) with exact P1 formulas per piece, which is several times faster than the
# general block route on a million elements and exactly symmetric.  The general route gives the
# same matrices to round-off (tested).  On a triangulated surface (SurfaceP1Space) the mass,
# stiffness and edge penalty use closed forms on the node graph instead (end of this module).
# ---------------------------------------------------------------------------------------------


def _sqrt_reference_mass(k: int) -> np.ndarray:
    """R (k, k) with R^T R = (I + 1 1^T) / ((k)(k+1)): the P1 mass matrix of a simplex of unit
    measure with k vertices (triangle: 1/12 (1 + delta_ij), tetrahedron: 1/20 (1 + delta_ij))."""
    ref = (np.eye(k) + np.ones((k, k))) / (k * (k + 1))
    w, Q = np.linalg.eigh(ref)
    return np.sqrt(w)[:, None] * Q.T


def _simplex_mass(space, vertices, parent, measure):
    """Gram rows of the exact mass matrix over simplices (triangles or tets) lying in elements."""
    lam = space.basis_at(vertices, parent)  # (m, k_vertices, k_dofs)
    R = _sqrt_reference_mass(vertices.shape[1])
    rows = R @ lam
    del lam
    rows *= np.sqrt(measure)[:, None, None]
    k = rows.shape[2]
    dofs = np.repeat(_compact(space.element_dofs[parent], space.n_dofs), rows.shape[1], axis=0)
    return gram(dofs, rows.reshape(-1, k), space.n_dofs, overwrite=True)


def _compact(dofs, n):
    """dofs as int32 when the numbers fit: the Gram rows repeat them, int32 halves that copy."""
    return dofs.astype(np.int32) if n < 2**31 else dofs


def _gradient_rows(space, grads, measure):
    """Gram rows sqrt(measure) * grads[:, :, d] for d = 0, 1, 2 (grads (n_el, k, 3))."""
    rows = (grads * np.sqrt(measure)[:, None, None]).transpose(0, 2, 1).reshape(-1, grads.shape[1])  # (3 n_el, k)
    dofs = np.repeat(_compact(space.element_dofs, space.n_dofs), 3, axis=0)
    return gram(dofs, rows, space.n_dofs, overwrite=True)


def mass(space) -> sp.csr_matrix:
    """Surface mass matrix M_ij = (phi_j, phi_i)_{S_h}, exact.

    On a cut space from the moments of each piece (:func:`_piece_mass`, three Gram rows per active
    tet); on a triangulated surface in closed form (:func:`_meshed_mass`); otherwise on each
    triangle T of S_h with the basis values Lambda (3 x k) at its vertices,
    M_T = Lambda^T |T|/12 (I + 1 1^T) Lambda (:func:`_simplex_mass`)."""
    if isinstance(space, SurfaceP1Space):
        return _meshed_mass(space)
    if isinstance(space, CutP1Space):
        return _piece_mass(space)
    vertices, parent, areas = space.surface_triangles()
    return _simplex_mass(space, vertices, parent, areas)


def _piece_mass(space) -> sp.csr_matrix:
    """The exact surface mass matrix of a cut space by the moments of the pieces: three Gram rows
    per active tet instead of three per triangle of S_h.

    The piece S_K of tet K is a plane polygon with area |S|, centroid c and in-plane orthonormal
    axes e1, e2 (orthogonal to n_h).  A P1 basis function is affine, lambda_i(x) = lambda_i(c) +
    g_i . (x - c) with g_i = grad lambda_i, and x - c = s e1 + t e2 on S_K; since the integral of
    x - c over S_K vanishes,

        int_{S_K} lambda_i lambda_j = |S| lambda_i(c) lambda_j(c) + a_i^T J a_j,
        a_i = (g_i . e1, g_i . e2),   J = int_{S_K} (s, t)^T (s, t)   (2 x 2).

    J is summed over the triangles T of the piece, each exactly:
    int_T q q^T = |T|/12 (sum_v q_v q_v^T + 9 qbar qbar^T) with q_v the in-plane coordinates of the
    vertices relative to c and qbar their mean.  With the Cholesky factor J = L L^T the rows
    sqrt|S| lambda(c) and L^T a give M_K = R^T R (3 x 4).  The same matrix as the triangle route
    (:func:`_simplex_mass`) to round-off (tested); at 853k active tets it builds 2.6M rows instead
    of 3.4M and needs no basis values at the 3.4M triangle vertices.
    """
    cut = space.cut
    tt, area = cut.triangle_tets, cut.triangle_areas
    m = space.n_elements
    piece = np.bincount(tt, weights=area, minlength=m)
    x = vertex_columns(cut.vertices, cut.triangles)  # x[v][d]: (T,), no (T, 3, 3) array
    centre = np.stack([np.bincount(tt, weights=area * (x[0][d] + x[1][d] + x[2][d]), minlength=m) for d in range(3)], axis=1)
    # a piece of zero area (collinear vertices) gets zero rows; its centre only has to be finite
    np.divide(centre, 3.0 * piece[:, None], out=centre, where=piece[:, None] > 0)
    e1, e2 = _plane_axes(space.element_normals)
    E1, E2, C = e1[tt], e2[tt], centre[tt]
    # in-plane coordinates of the triangle vertices relative to the piece centroid
    s = [sum((x[v][d] - C[:, d]) * E1[:, d] for d in range(3)) for v in range(3)]
    t = [sum((x[v][d] - C[:, d]) * E2[:, d] for d in range(3)) for v in range(3)]
    del x, E1, E2, C
    sbar, tbar = (s[0] + s[1] + s[2]) / 3.0, (t[0] + t[1] + t[2]) / 3.0
    w = area / 12.0
    Jss = np.bincount(tt, weights=w * (s[0] * s[0] + s[1] * s[1] + s[2] * s[2] + 9.0 * sbar * sbar), minlength=m)
    Jst = np.bincount(tt, weights=w * (s[0] * t[0] + s[1] * t[1] + s[2] * t[2] + 9.0 * sbar * tbar), minlength=m)
    Jtt = np.bincount(tt, weights=w * (t[0] * t[0] + t[1] * t[1] + t[2] * t[2] + 9.0 * tbar * tbar), minlength=m)
    del s, t, sbar, tbar
    L11 = np.sqrt(Jss)
    L21 = np.divide(Jst, L11, out=np.zeros(m), where=L11 > 0)
    L22 = np.sqrt(np.maximum(Jtt - L21 * L21, 0.0))  # the Schur complement, >= 0 up to round-off
    G = space.element_gradients
    a = np.einsum("mkd,md->mk", G, e1)
    b = np.einsum("mkd,md->mk", G, e2)
    rows = np.empty((m, 3, G.shape[1]))
    rows[:, 0] = space.basis_at(centre[:, None, :], np.arange(m))[:, 0] * np.sqrt(piece)[:, None]
    rows[:, 1] = L11[:, None] * a + L21[:, None] * b
    rows[:, 2] = L22[:, None] * b
    dofs = np.repeat(_compact(space.element_dofs, space.n_dofs), 3, axis=0)
    return gram(dofs, rows.reshape(-1, G.shape[1]), space.n_dofs, overwrite=True)


def _plane_axes(normals):
    """Unit vectors e1, e2 (m, 3) with (e1, e2, n) orthonormal: e1 from n crossed with the
    coordinate axis least aligned with n."""
    k = np.argmin(np.abs(normals), axis=1)
    axis = np.zeros_like(normals)
    axis[np.arange(len(k)), k] = 1.0
    e1 = cross(normals, axis)
    e1 /= np.linalg.norm(e1, axis=1)[:, None]
    return e1, cross(normals, e1)


def tangential_stiffness(space) -> sp.csr_matrix:
    """A_ij = (P_h grad phi_j, P_h grad phi_i)_{S_h}; on each element |K| (P_h G_j)·(P_h G_i),
    |K| the area of the surface part of the element.  On a triangulated surface in closed form,
    :func:`_meshed_stiffness`."""
    if isinstance(space, SurfaceP1Space):
        return _meshed_stiffness(space)
    return _gradient_rows(space, space.tangential_gradients, space.element_surface_areas)


def position_load(space) -> np.ndarray:
    """The right-hand sides of the mean curvature problem, b_ik = (grad_{S_h} x_k, grad_{S_h} phi_i)_{S_h},
    as an (n, 3) array, without assembling the stiffness matrix.

    The coordinates x_k are linear, so their P1 interpolant is exact on every element and
    grad_{S_h} x_k = P_h e_k; since P_h is a symmetric projection and grad_{S_h} phi_i is tangent,
    (P_h e_k) . grad_{S_h} phi_i = (grad_{S_h} phi_i)_k.  Hence

        b_i = sum_K |S_K| grad_{S_h} phi_i|_K,

    the area-weighted tangential gradients summed per dof: the same vector as A x_k with
    A = :func:`tangential_stiffness` (to round-off; tested), at the cost of one scatter instead of
    a sparse matrix product (20 times less than the product on a cut torus at spacing 0.05).
    Each element's contributions sum to |S_K| P_h grad(1) = 0, so sum_i b_i = 0 up to round-off
    (the zero integral of H_h).  On a triangulated surface the closed-form stiffness
    (:func:`_meshed_stiffness`, no gradients) times x is cheaper (25 against 90 ms at 295k nodes)
    and is used instead.
    """
    if isinstance(space, SurfaceP1Space):
        return _meshed_stiffness(space) @ space.dof_points
    if not isinstance(space, CutP1Space):
        raise TypeError(f"position_load integrates over a surface: give a SurfaceP1Space or a CutP1Space, not {type(space).__name__}")
    local = space.tangential_gradients * space.element_surface_areas[:, None, None]
    return assemble_vector(space.element_dofs, local, space.n_dofs)


def normal_gradient_penalty(space, h_power: float = 1.0) -> sp.csr_matrix:
    """s(u, v) = h^a (n_h . grad u, n_h . grad v)_{T_h} over the active tets (multiply by tau_N).

    The normal n_h is the piece normal of each active tet; ``h_power`` is a (default 1).
    """
    c = np.einsum("mkd,md->mk", space.element_gradients, space.element_normals)
    rows = c * np.sqrt(space.h**h_power * space.element_volumes)[:, None]
    return gram(space.element_dofs, rows, space.n_dofs)


def volume_mass(space) -> sp.csr_matrix:
    """(u, v) over the cut volume {phi_h < 0} (a :class:`~cutfem.spaces.CutVolumeP1Space`), exact:
    on each sub-tetrahedron |T|/20 (I + 1 1^T) in its vertex values."""
    vertices, parent, volumes = space.volume_tetrahedra()
    return _simplex_mass(space, vertices, parent, volumes)


def volume_stiffness(space) -> sp.csr_matrix:
    """(grad u, grad v) over the cut volume {phi_h < 0}: the inside volume of each element times G G^T."""
    vertices, parent, volumes = space.volume_tetrahedra()
    inside = np.bincount(parent, weights=volumes, minlength=len(space.element_dofs))
    return _gradient_rows(space, space.element_gradients, inside)


def load(space, f, degree: int = 4, measure: str = "surface", closest_point=None) -> np.ndarray:
    """Load vector b_i = (f, phi_i) over the measure, by quadrature of the given degree.

    ``f(x)`` takes points (m, q, 3) and returns (m, q) or (m, q, c) (then b is (n, c)).  With
    ``closest_point`` (a map x -> p(x)), f is evaluated as f o p (the extension f^e of SPEC §4).
    """
    quad = space.quadrature(measure, degree)
    x = quad.points if closest_point is None else closest_point(quad.points)
    fx = np.asarray(f(x), dtype=float)
    if fx.shape[:2] != quad.weights.shape:
        raise ValueError(f"f must return values of shape (m, q) or (m, q, c) for points (m, q, 3); got {fx.shape}")
    phi = space.basis_values(quad) * quad.weights[..., None]  # (m, q, k)
    local = np.einsum("mqk,mq...->mk...", phi, fx)
    return assemble_vector(space.element_dofs[quad.parent], local, space.n_dofs)


def _jump_gram(space, pairs, normals_pair, scale):
    """Gram matrix of the jumps c = (t1 . G_{K1}, t2 . G_{K2}) weighted by ``scale`` (>= 0): one row
    per facet on the dofs of K1 and K2 (shared dofs summed)."""
    G = space.element_gradients
    c = np.concatenate([np.einsum("fkd,fd->fk", G[pairs[:, s]], normals_pair[:, s]) for s in (0, 1)], axis=1)
    c *= np.sqrt(scale)[:, None]
    dofs = _compact(space.element_dofs, space.n_dofs)
    dofs = np.concatenate([dofs[pairs[:, 0]], dofs[pairs[:, 1]]], axis=1)
    return gram(dofs, c, space.n_dofs, overwrite=True)


def edge_jump_penalty(space, h: float | None = None) -> sp.csr_matrix:
    """J_E(u, v) = sum_E h ([t_E . grad u], [t_E . grad v])_E (multiply by tau_E).

    [t_E . grad u] = t_{E,K1} . grad u|K1 + t_{E,K2} . grad u|K2 with the outward conormals of the
    two surface elements; constant on E for P1, so the integral is |E| times the product of jumps.
    ``h`` defaults to the space's global mesh size.
    """
    h = space.h if h is None else h
    if isinstance(space, SurfaceP1Space):
        return _meshed_edge_penalty(space, h)
    pairs, conormals, lengths = space.edges()
    return _jump_gram(space, pairs, conormals, h * lengths)


def face_jump_penalty(space, h_power: float = 0.0) -> sp.csr_matrix:
    """J_F(u, v) = sum_F h^a ([n_F . grad u], [n_F . grad v])_F over interior faces of the active mesh
    (multiply by tau_F).  [n_F . grad u] = n_{F,T1}.grad u|T1 + n_{F,T2}.grad u|T2; a = ``h_power``
    (0 in the paper)."""
    pairs, n, areas = space.faces()
    normals_pair = np.stack([n, -n], axis=1)
    return _jump_gram(space, pairs, normals_pair, space.h**h_power * areas)


# ---------------------------------------------------------------------------------------------
# Closed forms on a triangulated surface (SurfaceP1Space).  On a flat triangle T with edge vectors
# e_k = x_{k+1} - x_k (indices mod 3) every P1 integral is a rational function of |T| and the dot
# products S_k = e_k . e_k, Q_k = e_k . e_{k+1} (SurfaceMesh.triangle_edge_dots).  Arrays of shape
# (M, 3) are indexed by the half-edge 3 t + k (local edge k of triangle t, from vertex k to k + 1,
# which is also the corner of vertex k); the half-edges after and before it in the triangle are
# the columns rotated by one, X[:, _NEXT] and X[:, _PREV].  Each matrix is a diagonal plus one
# value per pair of nodes, written straight into the cached CSR structure of the node graph
# (cutfem.assembly.SymmetricPattern): no quadrature, no sort, exactly symmetric.  The general
# routes above give the same matrices to round-off (tested).
# ---------------------------------------------------------------------------------------------

_NEXT = [1, 2, 0]
_PREV = [2, 0, 1]


def _meshed_mass(space) -> sp.csr_matrix:
    """Exact P1 mass matrix of S_h: M_T = |T|/12 (I + 1 1^T), i.e.

        M_ii = sum_{T at i} |T| / 6,   M_ij = sum_{T at edge ij} |T| / 12.
    """
    areas = space.element_areas
    diagonal = np.bincount(space.element_dofs.reshape(-1), weights=np.repeat(areas / 6.0, 3), minlength=space.n_dofs)
    et = space.mesh.edge_triangles
    return space.node_pattern().matrix(diagonal, (areas[et[:, 0]] + areas[et[:, 1]]) / 12.0)


def _meshed_stiffness(space) -> sp.csr_matrix:
    """P1 stiffness matrix of S_h (the cotangent formula in edge vectors):

        |T| grad lambda_i . grad lambda_j = e_{i+1} . e_{j+1} / (4 |T|),

    so vertex k of T adds S_{k+1} / (4|T|) to the diagonal and its local edge k, from vertex k to
    k + 1, adds Q_{k+1} / (4|T|) to that edge's entry.
    """
    S, Q = space.mesh.triangle_edge_dots
    quarter = 0.25 / space.element_areas[:, None]
    diagonal = np.bincount(space.element_dofs.reshape(-1), weights=(S[:, _NEXT] * quarter).reshape(-1), minlength=space.n_dofs)
    per_halfedge = (Q[:, _NEXT] * quarter).reshape(-1)
    h = space.mesh.edge_halfedges
    return space.node_pattern().matrix(diagonal, per_halfedge[h[:, 0]] + per_halfedge[h[:, 1]])


def _meshed_edge_penalty(space, h: float) -> sp.csr_matrix:
    """J_E of SPEC §3 on S_h in closed form: sum_E h |E| a a^T with a the jump coefficients.

    The outward conormal of triangle K at its edge k is t = e_k / |e_k| x n_K, and
    t . grad lambda_m = -e_k . e_{m+1} / (2 |K| |E|): at the start, the end and the opposite vertex
    of half-edge k,

        c_start = -Q_k / (2|K||E|),  c_end = -Q_{k-1} / (2|K||E|),  c_opp = -|E| / (2|K|)

    (e_{k-1} . e_k = e_k . e_{k+2}; the three sum to zero).  Edge E = [i, j] has the half-edges
    h1: i -> j in K1 (opposite vertex k) and its twin h2: j -> i in K2 (opposite l), so the jump
    [t_E . grad u] = a_i u_i + a_j u_j + a_k u_k + a_l u_l has a_i = c_start(h1) + c_end(h2),
    a_j = c_end(h1) + c_start(h2), a_k = c_opp(h1), a_l = c_opp(h2).  With b = sqrt(h |E|) a
    written per half-edge (b_start, b_end, b_opp), edge E adds b_x b_y to every pair {x, y} of its
    four nodes:

    * {i, j}: b_start(h1) b_end(h1); {k, l}: b_opp(h1) b_opp(h2)
      (:meth:`SurfaceP1Space.edge_stencil_pattern`);
    * the other two edges of each triangle: half-edge g gets b_end b_opp from the half-edge
      before it and b_opp b_start from the one after it;
    * the diagonal: corner g (vertex k of K, where half-edge g starts) gets b_start(g)^2 from the
      edge leaving it and b_opp^2 from the edge opposite to it, the half-edge after g.
    """
    mesh = space.mesh
    S, Q = mesh.triangle_edge_dots
    h1, h2 = mesh.edge_halfedges.T
    twin = np.empty(S.size, dtype=np.int64)
    twin[h1], twin[h2] = h2, h1
    # (M, 3) arrays, updated in place: at n = 768 each is 14 MB of fresh memory otherwise
    length = np.sqrt(S)  # |E| per half-edge
    cs = np.sqrt(length * h)  # sqrt(h |E|) ...
    cs /= length * space.element_areas[:, None]
    cs *= -0.5  # ... times -1 / (2 |K| |E|)
    buffer = Q[:, _PREV] * cs  # sqrt(h|E|) c_end
    b_start = buffer.reshape(-1)[twin]  # sqrt(h|E|) c_end of the twin ...
    b_start += np.multiply(Q, cs, out=buffer).reshape(-1)  # ... plus sqrt(h|E|) c_start
    b_end = b_start[twin]  # b at the end of h is b at the start of its twin
    b_opp = np.multiply(S, cs, out=buffer).reshape(-1)
    b_end *= b_opp  # what h gives to the half-edge after it
    to_prev = b_opp * b_start  # what h gives to the half-edge before it
    received = b_end.reshape(-1, 3)[:, _PREV]
    received += to_prev.reshape(-1, 3)[:, _NEXT]
    received = received.reshape(-1)
    on_edges = b_start[h1] * b_start[h2] + received[h1] + received[h2]
    opposite = b_opp.reshape(-1, 3)[:, _NEXT].reshape(-1)  # b_opp of the edge opposite each corner
    opposite *= opposite
    opposite += np.square(b_start, out=b_start)
    diagonal = np.bincount(space.element_dofs.reshape(-1), weights=opposite, minlength=space.n_dofs)
    return space.edge_stencil_pattern().matrix(diagonal, np.concatenate([on_edges, b_opp[h1] * b_opp[h2]]))
