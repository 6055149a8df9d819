"""The built-in terms: integrands of the form language (:mod:`cutfem.fem.forms`) with exact implementations.

:func:`mass`, :func:`stiffness`, :func:`tangential_stiffness`, :func:`face_jump_penalty` (J_F and
the bulk ghost penalty), :func:`edge_jump_penalty` (J_E), :func:`normal_gradient_penalty`,
:func:`nitsche` (symmetric Nitsche for Dirichlet data, with the outward normal of the field's side,
and its right-hand side :attr:`Nitsche.load`), :func:`interface_nitsche` (Hansbo-Hansbo coupling)
and the linear terms :func:`load`, :func:`position_load`, :func:`basis_integrals`.  Strong Dirichlet
conditions: :func:`apply_dirichlet`.  The mathematics is in docs/math.md §3, §4 and §7-§10.

Each term is ``integrand.on(measure, field, **parameters)`` for an :class:`~cutfem.fem.forms.Integrand`
defined here: its function is the term's mathematics, read by quadrature like a user integrand (the
parameters as ``w.gamma``, ``w.h_power``, the data as ``w.g``), and its ``exact`` implementation
(:mod:`cutfem.fem.closed_forms`: closed P1 formulas, Gram products E^T E, lattice and pair sums) is what
:func:`~cutfem.fem.forms.assemble` runs: several times faster than quadrature and exactly symmetric,
the same matrices to round-off (tested against :meth:`~cutfem.fem.forms.Form.by_quadrature`).  A
term is thus combined, scaled and assembled like any ``integrand * measure``; its parameters are
the term's own, given where it is made, and there only: the Nitsche term carries its penalty gamma
to its matrix, to its load (:attr:`Nitsche.load`) and to the advice on an indefinite matrix
(:attr:`~cutfem.fem.forms.Form.indefinite_hint`).  Each takes its measure and, on a product space,
``field=``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from . import element_kernels, high_order
from .assembly import block_diagonal, gram
from .closed_forms import (_element_symmetric, _gradient_matrix, _jump_gram, _kuhn_stiffness, _kuhn_tangential_stiffness,
                    _kuhn_volume_mass, _meshed_edge_penalty, _meshed_mass, _meshed_stiffness, _piece_mass, _piece_moments,
                    _point_load, _simplex_mass)
from .forms import Form, Integrand, Term, _field_index, _number, assemble
from ..geometry.measures import ElementVolume, FacetMeasure, Measure, MeshedSurface, SideVolume, SurfacePieces
from ..geometry.markers import CUT, NEG, POS, SIDES
from ..geometry.numbering import TET_EDGES
from .high_order import second_normal
from .pointwise import ZERO, VectorBasisField, _require_function, _value, dot, inner, jump
from .spaces import ProductSpace, VectorSpace

__all__ = [
    "mass",
    "stiffness",
    "tangential_stiffness",
    "face_jump_penalty",
    "edge_jump_penalty",
    "normal_gradient_penalty",
    "nitsche",
    "Nitsche",
    "interface_nitsche",
    "load",
    "position_load",
    "basis_integrals",
    "apply_dirichlet",
]


def _integrand(name, function, linear=False, **kwargs) -> Integrand:
    """A built-in term's integrand, named ``name`` in messages."""
    f = Integrand(function, linear, **kwargs)
    f.__name__ = name
    return f


def _componentwise(exact):
    """The exact implementation of a bilinear term that acts on each component of a vector field
    alike: on a :class:`~cutfem.fem.spaces.VectorSpace` the scalar field's matrix, summed into the
    scalar running sum (counted I_3 times by :class:`~cutfem.fem.assembly.VectorSum`) or returned as
    kron(I_3, A); the scalar term itself on a scalar field."""

    def on_field(term, space, into, scale):
        if not isinstance(space, VectorSpace):
            return exact(term, space, into, scale)
        A = exact(term, space.scalar, None if into is None else into.scalar, scale)
        return None if A is None else block_diagonal(A, 3)

    return on_field


def _componentwise_load(exact):
    """The exact implementation of a linear term on a vector field: the scalar term's vector (n, 3)
    of vector data (a function returning (m, q, 3)), one column per component, as (3 n,)."""

    def on_field(term, space):
        if not isinstance(space, VectorSpace):
            return exact(term, space)
        b = np.asarray(exact(term, space.scalar))
        if b.shape != (space.scalar.n_dofs, 3):
            raise ValueError(f"{term.integrand.__name__} on a vector field needs vector data, a function returning (m, q, 3) at "
                             f"points (m, q, 3); it gave {b.shape[1:] or 'one value'} per node")
        return b.T.reshape(-1)

    return on_field


def _same_elements(space, measure) -> bool:
    return measure.elements is space.elements


def _same_mesh(space, measure: MeshedSurface, what: str) -> None:
    """A clear error unless the field lives on the measure's surface mesh: a
    :class:`~cutfem.fem.spaces.SurfaceP1Space` of that mesh (the same object, or a mesh with the same
    points and triangles).  The closed forms on a triangulated surface read the field's mesh only,
    so a measure on another mesh would be ignored silently."""
    mesh = getattr(space, "mesh", None)
    if mesh is None:
        raise ValueError(f"{what} over the triangles of a surface mesh needs SurfaceP1Space(mesh) of that mesh; got {space!r}")
    other = measure.mesh
    if mesh is not other and not (np.array_equal(mesh.points, other.points) and np.array_equal(mesh.triangles, other.triangles)):
        raise ValueError(f"{what}: the measure is over {other!r}, but the field lives on another mesh (other points or "
                         f"triangles), {mesh!r}; integrate over mesh.ds() of the field's own mesh")


def _require(measure, kinds, what):
    if not isinstance(measure, kinds):
        names = " or ".join(k.__name__ for k in (kinds if isinstance(kinds, tuple) else (kinds,)))
        raise TypeError(f"{what} integrates over a {names} measure, got {measure!r}")


# ---------------------------------------------------------------------------------------------
# mass and stiffness
# ---------------------------------------------------------------------------------------------


def _mass_exact(term, space, into, scale):
    measure = term.measure
    if isinstance(measure, MeshedSurface):
        _same_mesh(space, measure, "mass")
        return _meshed_mass(space, into, scale)
    if isinstance(measure, SurfacePieces):
        if _same_elements(space, measure):
            return _piece_mass(space, into, scale)
        c = measure.cut
        el = space.local_elements(measure, c.triangle_tets)
        return _simplex_mass(space, c.triangle_points, el, c.triangle_areas)
    if isinstance(measure, (SideVolume, ElementVolume)):
        if _same_elements(space, measure) and into is not None:
            return _kuhn_volume_mass(space, measure, into, scale)
    if isinstance(measure, SideVolume):
        vertices = measure.cell_vertices()
        return _simplex_mass(space, vertices, space.local_elements(measure, measure.cell_parent), measure.cell_volumes)
    if isinstance(measure, ElementVolume):
        es = measure.elements
        return _simplex_mass(space, es.vertices, space.local_elements(measure, np.arange(es.n_elements)), es.volumes)
    raise TypeError(f"mass integrates over cells (a surface or a volume), not over {measure!r}")


_MASS = _integrand("mass", lambda u, v, w: inner(u, v), symmetric=True, exact=_componentwise(_mass_exact),
                   high_order=high_order.mass_blocks)


def mass(measure: Measure, field=None) -> Form:
    """(u, v) over ``measure``, exact for P1: on S_h of a cut per piece
    (:func:`~cutfem.fem.closed_forms._piece_mass`), on a triangulated surface in closed form, over a volume of
    a structured box's element set per lattice edge for the whole tets
    (:func:`~cutfem.fem.closed_forms._kuhn_volume_mass`), otherwise on each simplex T of the measure
    (triangles of S_h, sub-tets of a side, whole tets) with the basis values Lambda at its vertices,
    M_T = Lambda^T |T|/((k)(k+1)) (I + 1 1^T) Lambda."""
    return _MASS.on(measure, field)


def _stiffness_exact(term, space, into, scale):
    measure = term.measure
    es = measure.elements
    weights = measure.part_volumes
    if term.params["h_power"] != 0:
        weights = weights * measure.h ** term.params["h_power"]
    if _same_elements(space, measure):  # no gathered copy of the gradients
        if into is not None:
            return _kuhn_stiffness(space, weights, into, scale)
        return _gradient_matrix(space, space.gradients_of, weights)
    el = space.local_elements(measure, np.arange(es.n_elements))
    return _gradient_matrix(space, lambda cells: space.gradients_of(el[cells]), weights, el)


_STIFFNESS = _integrand("stiffness", lambda u, v, w: w.h**w.h_power * inner(u.grad, v.grad), symmetric=True,
                        exact=_componentwise(_stiffness_exact), high_order=high_order.stiffness_blocks)


def stiffness(measure: Measure, field=None, h_power: float = 0) -> Form:
    """(grad u, grad v) over a volume measure, or with ``h_power`` = a the cellwise weighted
    sum_T h_T^a (grad u, grad v)_{T ∩ side} (a = 2: the Brezzi-Pitkaranta pressure stabilization):
    |T ∩ side| h_T^a G G^T per tet (the P1 gradients are constant), for a side of the cut
    (:class:`~cutfem.geometry.measures.SideVolume`) or whole tets; summed per lattice edge on a
    structured box (:func:`~cutfem.fem.closed_forms._kuhn_stiffness`), as a Gram product otherwise."""
    _require(measure, (SideVolume, ElementVolume), "stiffness")
    return _STIFFNESS.on(measure, field, h_power=_number("h_power", h_power))


def _tangential_exact(term, space, into, scale):
    measure = term.measure
    if isinstance(measure, MeshedSurface):
        _same_mesh(space, measure, "tangential_stiffness")
        into.add(*_meshed_stiffness(space), scale=scale)
        return None
    if _same_elements(space, measure):
        if into is not None:
            return _kuhn_tangential_stiffness(space, measure, into, scale)
        return _gradient_matrix(space, space.tangential_gradients_of, measure.piece_areas)
    es = measure.elements
    el = space.local_elements(measure, np.arange(es.n_elements))
    G, n = space.gradients_of(el), measure.normals
    tG = G - np.einsum("mkd,md->mk", G, n)[..., None] * n[:, None, :]
    return _gradient_matrix(space, lambda cells: tG[cells], measure.piece_areas, el)


_TANGENTIAL = _integrand("tangential_stiffness", lambda u, v, w: inner(u.tgrad, v.tgrad), symmetric=True,
                         exact=_componentwise(_tangential_exact), high_order=high_order.tangential_blocks)


def tangential_stiffness(measure: Measure, field=None) -> Form:
    """(P_h grad u, P_h grad v) over a surface: on each piece |K| (P_h G_j)·(P_h G_i), |K| the area
    of the piece and P_h = I - n_h n_h^T; on a triangulated surface in closed form
    (:func:`~cutfem.fem.closed_forms._meshed_stiffness`); on the cut tets of a structured box per lattice edge
    (:func:`~cutfem.fem.closed_forms._kuhn_tangential_stiffness`)."""
    _require(measure, (SurfacePieces, MeshedSurface), "tangential_stiffness")
    return _TANGENTIAL.on(measure, field)


# ---------------------------------------------------------------------------------------------
# linear terms
# ---------------------------------------------------------------------------------------------


def _position_load_exact(term, space):
    measure = term.measure
    if isinstance(measure, MeshedSurface):
        _same_mesh(space, measure, "position_load")
        out = np.zeros((space.n_dofs, 3))
        element_kernels.meshed_position_load(space.dof_points, space.element_dofs, out)
        return out
    if not _same_elements(space, measure):
        raise ValueError("position_load needs the field on the cut tets, CutSpace(cut, CUT)")
    out = np.zeros((space.n_dofs, 3))
    table, types = space.gradient_lookup()
    element_kernels.tangential_gradient_sums(space.element_dofs, table, types, np.ascontiguousarray(space.element_normals, dtype=float),
                                             np.ascontiguousarray(measure.piece_areas, dtype=float), out)
    return out


def _position_integrand(v, w):
    """(P_h e_k, grad_S v) = (grad_S v)_k: the tangential gradient itself, one column per coordinate;
    of a vector test function the sum over k of (grad_S v_k)_k, the trace of its tangential gradient."""
    return np.einsum("...kk->...", v.tgrad) if isinstance(v, VectorBasisField) else v.tgrad


_POSITION_LOAD = _integrand("position_load", _position_integrand, linear=True, degree=1,
                            exact=_componentwise_load(_position_load_exact), high_order=high_order.position_load_vectors)


def position_load(measure: Measure, field=None) -> Form:
    """The right-hand sides of the mean curvature problem, b_ik = (grad_{S_h} x_k, grad_{S_h} phi_i)_{S_h},
    an (n, 3) array, without assembling the stiffness matrix.

    The coordinates x_k are linear, so their P1 interpolant is exact on every element and
    grad_{S_h} x_k = P_h e_k; since P_h is a symmetric projection and grad_{S_h} phi_i is tangent,
    (P_h e_k) . grad_{S_h} phi_i = (grad_{S_h} phi_i)_k.  Hence

        b_i = sum_K |S_K| grad_{S_h} phi_i|_K,

    the area-weighted tangential gradients summed per dof: the same vector as A x_k with A the
    tangential stiffness (to round-off; tested), at the cost of one compiled pass over the elements
    (:func:`cutfem.fem.element_kernels.tangential_gradient_sums`; on a triangulated surface
    :func:`cutfem.fem.element_kernels.meshed_position_load`, from the node positions alone) instead of a sparse
    matrix product.  Each element's contributions sum to |S_K| P_h grad(1) = 0, so sum_i b_i = 0
    up to round-off (the zero integral of H_h).
    """
    _require(measure, (SurfacePieces, MeshedSurface), "position_load")
    return _POSITION_LOAD.on(measure, field)


def _basis_integrals_exact(term, space):
    measure = term.measure
    if isinstance(space, VectorSpace):
        raise TypeError("basis_integrals is (1, v) of a scalar field; on a vector field integrate the component you need, "
                        "basis_integrals(measure) on its scalar space")
    if isinstance(measure, MeshedSurface):
        _same_mesh(space, measure, "basis_integrals")
        return np.bincount(space.element_dofs.reshape(-1), weights=np.repeat(space.element_areas / 3.0, 3),
                           minlength=space.n_dofs)
    if isinstance(measure, SurfacePieces) and _same_elements(space, measure):
        cut, out = measure.cut, np.zeros(space.n_dofs)
        table, types = space.gradient_lookup()
        element_kernels.piece_integrals(cut.vertices, cut.triangles, cut.triangle_tets, cut.triangle_areas, space.dof_points,
                                        space.element_dofs, table, types, space.element_dofs, out)
        return out
    return assemble(load(lambda x: np.ones(x.shape[:2]), measure, degree=1), space)


_BASIS_INTEGRALS = _integrand("basis_integrals", lambda v, w: v, linear=True, degree=1, exact=_basis_integrals_exact)


def basis_integrals(measure: Measure, field=None) -> Form:
    """The vector (int phi_i)_i over a cell measure, i.e. (1, v): on S_h of a cut per triangle of the
    pieces, |T| lambda_i(centroid) (:func:`cutfem.fem.element_kernels.piece_integrals`, one compiled pass); on a
    triangulated surface |T|/3 per vertex; otherwise :func:`load` of 1 at degree 1 (exact for P1).
    Its sum is the measure's size; it is 1^T M for the mass matrix M over the same measure (to
    round-off), without assembling M."""
    if isinstance(measure, FacetMeasure):
        raise TypeError("basis_integrals integrates over cells (a volume or a surface), not over facets")
    _require(measure, Measure, "basis_integrals")
    return _BASIS_INTEGRALS.on(measure, field)


def _times(g, x):
    """The data of a load times its test values: g (m, q) or (m, q, c) times scalar values x (m, q)
    (c loads at once), g . x for vector values x (m, q, 3) (g (m, q, 3), vector data)."""
    x = _value(x)
    if x.ndim == 3:
        if g.ndim != 3 or g.shape[2] != 3:
            raise ValueError(f"the data of a load on a vector field must be vectors, shape (m, q, 3); got {g.shape}")
        return dot(g, x)
    return g * (x if g.ndim == 2 else x[..., None])


def _load_exact(term, space):
    def local(quad, el, phi, fw):
        if phi.strides[0] == 0 and fw.ndim == 2:  # every cell whole: one basis table
            return fw @ phi[0]
        return np.einsum("mqk,mq...->mk...", phi, fw)

    return _point_load(space, term.measure, term.integrand.degree, term.params["f"], "the load f(x)", local)


def load(f, measure: Measure, degree: int = 4, closest_point=None, field=None) -> Form:
    """(f, v) over ``measure`` (a cell measure: a side's volume, whole tets, S_h or a triangulated
    surface) by quadrature of the given degree.

    ``f(x)`` takes points (m, q, 3) and returns real, finite values (checked) of shape (m, q) or
    (m, q, c) (then the vector is (n, c)); with ``closest_point`` (a map x -> p(x)) it is evaluated
    as f o p, the extension f^e of docs/math.md §4.
    Block by block of cells, b_{K,k} = sum_q w_q f(x_q) phi_k(x_q): one product of the weighted
    values with the basis values (the rule's own barycentric coordinates on whole elements)."""
    _require_function(f, "load: f")
    if closest_point is not None:
        _require_function(closest_point, "load: closest_point")
    g = f if closest_point is None else (lambda x: f(closest_point(x)))
    if isinstance(measure, FacetMeasure):
        raise TypeError("load integrates over cells (a volume or a surface); for a facet term write a linear_form integrand")
    _require(measure, Measure, "load")
    integrand = _integrand("load", lambda v, w: _times(w.at(w.f), v), linear=True, degree=degree,
                           exact=_componentwise_load(_load_exact), high_order=high_order.load_vectors)
    return integrand.on(measure, field, f=g)


# ---------------------------------------------------------------------------------------------
# stabilizations
# ---------------------------------------------------------------------------------------------


def _face_jump_exact(term, space, into, scale):
    measure, h_power = term.measure, term.params["h_power"]
    f = measure.facets
    if f.n_facets == 0:
        return None  # nothing to add: the zero matrix, as a user form over the same facets gives
    if measure.elements is space.elements:
        pairs = f.pairs
    else:
        pairs = np.stack([space.local_elements(measure, f.pairs[:, s]) for s in (0, 1)], axis=1)
    if into is not None:  # face-adjacent tets of a structured box: normals and areas computed face by face
        table, types = space.gradient_lookup()
        into.add_face_jumps(pairs, f.opposite, np.ones(1) if h_power == 0 else _h_power(f.h, h_power, "face_jump_penalty"),
                            space.elements.volumes, space.element_dofs, table, types, scale)
        return None
    n, factor = f.normals_areas()
    if h_power != 0:
        factor *= _h_power(f.h, h_power, "face_jump_penalty")
    return _jump_gram(space, pairs, n, n, -1.0, factor)


def _face_jump_integrand(u, v, w):
    """h^a [n . grad u][n . grad v] + h^(a+2) / 4 [n^T H(u) n][n^T H(v) n]: the jumps of the normal
    derivatives of order j = 1, 2, weighted h^(a + 2(j - 1)) / (j!)^2; P1 Hessians are ZERO, so for
    P1 it is the first term alone."""
    first = w.h**w.h_power * inner(dot(jump(u.grad), w.n), dot(jump(v.grad), w.n))
    second = inner(second_normal(jump(u.hess), w.n), second_normal(jump(v.hess), w.n))
    if second is ZERO:
        return first
    return first + (0.25 * w.h ** (w.h_power + 2.0)) * second


# [n_F . grad u] = n_F . (grad u^- - grad u^+), n_F from the minus to the plus tet (of each component: grad u n_F)
_FACE_JUMP = _integrand("face_jump_penalty", _face_jump_integrand, symmetric=True, exact=_componentwise(_face_jump_exact),
                        high_order=high_order.face_jump_blocks)


def face_jump_penalty(measure: FacetMeasure, h_power: float = 0.0, field=None) -> Form:
    """sum_F h_F^a ([n_F . grad u], [n_F . grad v])_F over a facet set, with the local h_F (the
    longest edge of F) and a = ``h_power``; on a field of order k the jumps of the normal
    derivatives of every order j <= k, sum_j h_F^(a + 2(j - 1)) / (j!)^2 ([d_n^j u], [d_n^j v])_F
    (docs/math.md §18: with a = 1 the ghost penalty of order k, weights h^(2j - 1) / (j!)^2), by
    quadrature of degree 2k.

    [n_F . grad u] = n_{F,T1}.grad u|T1 + n_{F,T2}.grad u|T2 with outward unit face normals; for P1
    it is constant on F, so the integral is |F| times the product of jumps.  Over the interior faces
    of the cut tets with a = 0 this is the face stabilization J_F of the mean curvature problem
    (docs/math.md §3); over the ghost faces of a side with a = 1 it is the Burman-Hansbo ghost
    penalty of a bulk field (§7), to be multiplied by gamma_g.  ``h_power`` is one real, finite
    number for which every h_F^a is a finite, nonzero float (else a ValueError).  An empty facet set
    gives the zero matrix.

    Meaningful coefficients (the problems check them, :mod:`cutfem.problems.common`).  As a ghost
    penalty (a = 1) beside a stiffness both scale as h^3 per tet, so gamma_g is a number: about
    0.01-1; its consistency error grows with it and it locks u_h to linear functions across the
    ghost faces as it grows (poisson-cut's L2 error 10 times the default's at 1e6).  As J_F beside a
    surface mass matrix (entries O(s^2) at spacing s, J_F's O(h^a)) the weight tau_F s^a counts:
    below 1e-3 the small pieces are barely controlled (the error grows like its inverse), below
    1e-6 not at all; above 1e6 s^2 the mass is lost beside it in round-off."""
    _require(measure, FacetMeasure, "face_jump_penalty")
    return _FACE_JUMP.on(measure, field, h_power=_number("h_power", h_power))


def _edge_jump_exact(term, space, into, scale):
    measure, h = term.measure, term.params["h_edge"]
    hh = space.h if h is None else h
    _positive(h=hh)
    if isinstance(measure, MeshedSurface):
        _same_mesh(space, measure, "edge_jump_penalty")
        into.add(*_meshed_edge_penalty(space, hh), scale=scale)
        return None
    if not _same_elements(space, measure):
        raise ValueError("edge_jump_penalty needs the field on the cut tets, CutSpace(cut, CUT)")
    c = measure.cut
    t = c.surface_edge_conormals
    # the pieces along an edge of S_h need not lie in face-adjacent tets: Gram products, not lattice slots
    return _jump_gram(space, c.surface_edge_tets, t[:, 0], t[:, 1], 1.0, hh * c.surface_edge_lengths)


def _edges_only(u, v, w):
    raise TypeError("edge_jump_penalty integrates over the edges between surface elements, which no quadrature measure covers: "
                    "it has its exact P1 form only (on P2 fields stabilize with face_jump_penalty or normal_gradient_penalty)")


_EDGE_JUMP = _integrand("edge_jump_penalty", _edges_only, symmetric=True, exact=_componentwise(_edge_jump_exact))


def edge_jump_penalty(measure: Measure, h: float | None = None, field=None) -> Form:
    """J_E(u, v) = sum_E h ([t_E . grad u], [t_E . grad v])_E over the edges of a surface, between
    neighbouring pieces of S_h (cut) or triangles (meshed).

    [t_E . grad u] = t_{E,K1} . grad u|K1 + t_{E,K2} . grad u|K2 with the outward conormals of the
    two surface elements; constant on E for P1, so the integral is |E| times the product of jumps.
    ``h`` defaults to the field's global mesh size (docs/math.md §3 asks for exactly that value);
    either must be a positive number.  The edges are no quadrature measure: this term has its exact
    implementation only."""
    _require(measure, (SurfacePieces, MeshedSurface), "edge_jump_penalty")
    if h is not None:
        _positive(h=h)
    return _EDGE_JUMP.on(measure, field, h_edge=h)


def _normal_gradient_exact(term, space, into, scale):
    measure, h_power = term.measure, term.params["h_power"]
    es = measure.elements
    el = space.local_elements(measure, np.arange(es.n_elements))
    c = np.einsum("mkd,md->mk", space.gradients_of(el), measure.normals)
    rows = c * np.sqrt(_h_power(es.h, h_power, "normal_gradient_penalty") * es.volumes)[:, None]
    return gram(space.element_dofs[el], rows, space.n_dofs)


_NORMAL_GRADIENT = _integrand("normal_gradient_penalty",
                              lambda u, v, w: w.h**w.h_power * inner(dot(u.grad, w.n), dot(v.grad, w.n)), symmetric=True,
                              exact=_componentwise(_normal_gradient_exact), high_order=high_order.normal_gradient_blocks)


def normal_gradient_penalty(measure: ElementVolume, h_power: float = 1.0, field=None) -> Form:
    """s(u, v) = sum_T h_T^a (n_h . grad u, n_h . grad v)_T over whole tets that carry a normal n_h
    (the cut tets: ``cut.dx(CUT)``), with the local h_T and a = ``h_power`` (one real, finite number
    for which every h_T^a is a finite, nonzero float, else a ValueError; multiply by tau_N)."""
    _require(measure, ElementVolume, "normal_gradient_penalty")
    h_power = _number("h_power", h_power)
    if measure.normals is None:
        raise ValueError("normal_gradient_penalty needs tets with a normal n_h: integrate over cut.dx(CUT)")
    return _NORMAL_GRADIENT.on(measure, field, h_power=h_power)


# ---------------------------------------------------------------------------------------------
# Nitsche
# ---------------------------------------------------------------------------------------------


def _side_of(space):
    """NEG or POS for a bulk field on one side's element set of its cut (``CutSpace(cut, NEG)`` or
    ``CutSpace(cut, POS)``: the set is the cut's own, :meth:`~cutfem.geometry.cut.CutMesh.elements`), else
    None (the cut tets, another element set, a surface mesh)."""
    cut, es = getattr(space, "cut", None), getattr(space, "elements", None)
    side = getattr(es, "name", None)
    if cut is None or side not in SIDES:
        return None
    return side if cut.elements(side) is es else None


def _outward_sign(space, measure: SurfacePieces, what: str) -> float:
    """The outward unit normal of the field's side on Gamma_h is ``sign * n_h`` (n_h points from NEG
    to POS): +1 for a field of NEG, -1 for a field of POS.  A field on an extended domain, the NEG
    side of another cut of the same background whose tets hold every cut tet of the measure (the
    active mesh of a moving domain, :mod:`cutfem.fem.moving`), has the measure's NEG side as its
    domain: +1.  A clear error for any other field: its outward normal is not defined."""
    side = _side_of(space)
    if side is not None and space.cut is measure.cut:
        return 1.0 if side == NEG else -1.0
    if side == NEG and space.cut is not measure.cut:
        cut_tets = measure.cut.elements(CUT)
        if np.all(space.elements.contains(cut_tets.tet_ids)):
            return 1.0
        raise ValueError(f"{what}: the field lives on the NEG side of another cut whose tets do not hold every cut tet of "
                         f"the measure ({space!r}); extend its domain (a larger strip) so that it covers Gamma_h")
    raise ValueError(f"{what} imposes a condition on Gamma_h for a bulk field of one side of the same cut, "
                     f"CutSpace(cut, NEG) or CutSpace(cut, POS), or of an extended domain holding the cut; got {space!r}")


def _nitsche_advice(params, form) -> str:
    """The fix of an indefinite Nitsche system: the penalty gamma is below its stability bound, which
    holds uniformly in the cut only with a ghost penalty; without one (no face penalty in the form)
    the bound grows without limit on small cut elements."""
    hint = f"raise the Nitsche penalty (gamma {params['gamma']:g} is below its stability bound)"
    if not any(c != 0 and term.integrand is _FACE_JUMP for c, term in form.terms):
        hint += (" or add a ghost penalty (the form has none: without it the bound grows without limit on the small cut "
                 "elements; gamma_g * face_jump_penalty(cut.dF(cut.ghost_facets(side)), h_power=1), gamma_g about 0.1)")
    return hint


def _nitsche_side(space, term):
    """The sign of the outward normal of the term's field, for its integrand (``w.outward``)."""
    return {"outward": _outward_sign(term.field_space(space), term.measure, "nitsche")}


def _nitsche_exact(term, space, into, scale):
    measure, gamma = term.measure, term.params["gamma"]
    sign = _outward_sign(space, measure, "nitsche")
    cut = measure.cut
    edges, diagonal, p = _piece_moments(cut)
    es = cut.elements(CUT)
    el = space.local_elements(measure, np.arange(es.n_elements))
    g = np.einsum("mkd,md->mk", space.gradients_of(el), es.normals)
    if sign < 0:
        g = -g
    factor = (gamma / es.h)[:, None]
    i, j = TET_EDGES[:, 0], TET_EDGES[:, 1]
    edges = edges * factor - (p[:, i] * g[:, j] + g[:, i] * p[:, j])
    diagonal = diagonal * factor - 2.0 * p * g
    return _element_symmetric(space, el, edges, diagonal, into, scale)


def _nitsche_matrix(u, v, w):
    n = w.outward * w.n  # of a vector field, the normal derivative of each component: grad u n
    return -inner(dot(u.grad, n), v) - inner(dot(v.grad, n), u) + inner(w.gamma / w.h * u, v)


def _nitsche_load_exact(term, space):
    measure, gamma = term.measure, term.params["gamma"]
    sign = _outward_sign(space, measure, "nitsche")

    def local(quad, el, phi, gw):
        dn = sign * np.einsum("mkd,md->mk", space.gradients_of(el), quad.normal)
        penalty = (gamma / measure.h[quad.parent]).reshape((-1,) + (1,) * (gw.ndim - 1))
        return np.einsum("mqk,mq...->mk...", phi, gw * penalty) - np.einsum("mk,m...->mk...", dn, gw.sum(axis=1))

    return _point_load(space, measure, term.integrand.degree, term.params["g"], "nitsche: g(x)", local)


_NITSCHE = _integrand("nitsche", _nitsche_matrix, symmetric=True, exact=_componentwise(_nitsche_exact), prepare=_nitsche_side,
                      advice=_nitsche_advice,
                      high_order=lambda term, V: high_order.nitsche_blocks(term, V, _outward_sign(V, term.measure, "nitsche")))
_NITSCHE_LOAD = _integrand("nitsche load", lambda v, w: _times(w.at(w.g), w.gamma / w.h * v - dot(v.grad, w.outward * w.n)),
                           linear=True, exact=_componentwise_load(_nitsche_load_exact), prepare=_nitsche_side,
                           high_order=lambda term, V: high_order.nitsche_load_vectors(term, V, _outward_sign(V, term.measure, "nitsche")))


class Nitsche(Form):
    """The symmetric Nitsche terms of u = g on Gamma, a bilinear form, with their right-hand side
    :attr:`load`: one penalty ``gamma`` for both and for the advice on an indefinite matrix
    (:attr:`~cutfem.fem.forms.Form.indefinite_hint`).  Made by :func:`nitsche` (``matrix`` and
    ``rhs`` its integrands) and :func:`cutfem.fem.elasticity.elasticity_nitsche` (those of linear
    elasticity, with their ``params`` mu and lam beside gamma)."""

    def __init__(self, measure, gamma, g, field, matrix=_NITSCHE, rhs=_NITSCHE_LOAD, params=None):
        self.params = {"gamma": gamma, **(params or {})}
        super().__init__([(1.0, Term(matrix, measure, field, self.params))], False)
        self.measure, self.gamma, self.g, self.field, self._rhs = measure, gamma, g, field, rhs

    @property
    def load(self) -> Form:
        """The Nitsche right-hand side of u = g: -(g, n . grad v)_Gamma + (gamma / h) (g, v)_Gamma, with
        the same gamma, h and outward normal n as the matrix, ``g(x)`` evaluated at the quadrature
        points of Gamma_h (degree 4; docs/math.md §8).  ``g`` returns (m, q), or (m, q, c) for c
        right-hand sides at once (the vector is then (n, c)); on a vector field
        (:class:`~cutfem.fem.spaces.VectorSpace`) it returns vectors (m, q, 3) and the vector is
        (3 n,).  Its values must be real and finite.  Of :func:`cutfem.fem.elasticity.elasticity_nitsche`:
        -(g, sigma(v) n)_Gamma + ((2 mu + lam) gamma / h) (g, v)_Gamma.

        Block by block of the triangles of S_h, with weights w_q, basis values phi_k and the constant
        n . grad phi_k of the cut tet: b_k = sum_q w_q g(x_q) (gamma / h_T phi_k(x_q) - n . grad phi_k)."""
        if self.g is None:
            raise ValueError("this Nitsche term has no boundary data: make it with nitsche(measure, gamma, g=...) for its load")
        return Form([(1.0, Term(self._rhs, self.measure, self.field, {**self.params, "g": self.g}))], True)


def nitsche(measure: SurfacePieces, gamma: float = 10.0, g=None, field=None) -> Nitsche:
    """Symmetric Nitsche terms for u = g on Gamma (Burman-Hansbo, docs/math.md §8):

        -(n . grad u, v)_Gamma - (u, n . grad v)_Gamma + (gamma / h) (u, v)_Gamma,

    n the outward unit normal of the field's domain and h the local h_T of the cut tet.  The side
    comes from the field: n = n_h (from NEG to POS) for ``CutSpace(cut, NEG)``, n = -n_h for
    ``CutSpace(cut, POS)`` (the outer domain); any other field is refused (:func:`_outward_sign`).
    With the data ``g`` (a function of the points) the matching right-hand side is the returned
    form's :attr:`~Nitsche.load`, with the same gamma.  On a vector field
    (:class:`~cutfem.fem.spaces.VectorSpace`) the terms act on each component, -(grad u n, v) - ...,
    and the matrix is kron(I_3, N) of the scalar one.  gamma (a positive number) must exceed an
    inverse-estimate constant, or the matrix is indefinite: the form's
    :attr:`~cutfem.fem.forms.Form.indefinite_hint` says so for the solver, with gamma's value.

    Exact for P1, per cut tet K with the piece S_K (area |S|, centroid c): grad u is constant and
    int_{S_K} lambda_i = |S| lambda_i(c), so the element matrix is

        N_K = -(p g^T + g p^T) + (gamma / h_T) M_K,   p_i = |S| lambda_i(c),  g_j = n . grad lambda_j,

    with M_K the exact piece mass matrix and p from :func:`~cutfem.fem.closed_forms._piece_moments`, summed
    by :func:`~cutfem.fem.closed_forms._element_symmetric` (exactly symmetric).  The same matrix as the
    integrand with quadrature of degree 2 to round-off (tested)."""
    _positive(gamma=gamma)
    _require(measure, SurfacePieces, "nitsche")
    if g is not None:
        _require_function(g, "nitsche: g")
    return Nitsche(measure, gamma, g, field)


def interface_nitsche(measure: SurfacePieces, a_neg: float, a_pos: float, gamma: float = 10.0, weights: str = "harmonic",
                      fields=(0, 1)) -> Form:
    """The Nitsche coupling of two fields across Gamma (Hansbo-Hansbo, docs/math.md §9):

        -({a n . grad u}, [v]) - ([u], {a n . grad v}) + (lambda / h) ([u], [v])   over Gamma_h,

    [w] = w_NEG - w_POS, {w} = k_NEG w_NEG + k_POS w_POS, n from NEG to POS and h the local h_T.
    ``weights="harmonic"``: k_NEG = a_POS / (a_NEG + a_POS) (and k_POS = 1 - k_NEG), robust in the
    contrast; ``weights="volume"``: k_i = |T ∩ Omega_i| / |T| per cut tet.  The penalty is
    lambda = 2 gamma (k_NEG^2 a_NEG + k_POS^2 a_POS), the weight that bounds the flux average by the
    energy of both sides; for harmonic weights it equals gamma times the harmonic mean
    2 a_NEG a_POS / (a_NEG + a_POS).  An integrand evaluated by quadrature (no exact
    implementation), with gamma its parameter ``w.gamma``; the form names gamma when its matrix is
    indefinite (:attr:`~cutfem.fem.forms.Form.indefinite_hint`).

    ``fields = (f_NEG, f_POS)`` (positions or names) are the NEG field, then the POS field, of a
    :class:`~cutfem.fem.spaces.ProductSpace`: ``CutSpace(cut, NEG)`` and ``CutSpace(cut, POS)`` of
    the measure's cut.  The rule is checked when the form is assembled, never adapted: two fields in
    the other order, the same field twice, a field of another element set or a single space are
    refused with the fix (e.g. ``fields=(1, 0)`` for ``ProductSpace(V_pos, V_neg)``)."""
    _require(measure, SurfacePieces, "interface_nitsche")
    _positive(a_neg=a_neg, a_pos=a_pos, gamma=gamma)
    if isinstance(fields, str) or np.ndim(fields) != 1 or len(fields) != 2:
        raise ValueError(f"fields must be a pair (NEG field, POS field) of positions or names, got {fields!r}")
    if weights == "harmonic":
        k_neg = np.full(measure.elements.n_elements, a_pos / (a_neg + a_pos))
    elif weights == "volume":
        k_neg = measure.side_fraction(NEG)
    else:
        raise ValueError(f"weights must be 'harmonic' or 'volume', got {weights!r}")
    k_pos = 1.0 - k_neg
    two_s = 2.0 * (k_neg**2 * a_neg + k_pos**2 * a_pos)  # lambda / gamma; gamma * (2 s) is 2 gamma s to the bit

    def prepare(space, term):
        """The positions of the NEG and the POS field in ``space``, checked."""
        if not isinstance(space, ProductSpace):
            raise TypeError(f"interface_nitsche couples two fields: assemble it on ProductSpace(V_neg, V_pos), not on {space!r}")
        k = [_field_index(space, f) for f in fields]
        if k[0] == k[1]:
            raise ValueError(f"interface_nitsche: fields={tuple(fields)!r} names the same field twice; give the NEG field, "
                             "then the POS field, e.g. fields=(0, 1)")
        if any(isinstance(space.fields[i], VectorSpace) for i in k):
            raise TypeError("interface_nitsche couples two scalar fields; for vector fields write the coupling as an integrand "
                            "(dot(u.grad, w.n) is the normal derivative of each component)")
        sides = [_side_of(space.fields[i]) if getattr(space.fields[i], "cut", None) is measure.cut else None for i in k]
        if sides != [NEG, POS]:
            where = ", ".join(f"field {f!r} on {getattr(getattr(space.fields[i], 'elements', None), 'name', space.fields[i])!r}"
                              for f, i in zip(fields, k))
            fix = (f"pass fields=({fields[1]!r}, {fields[0]!r})" if sides == [POS, NEG] else
                   "give the fields CutSpace(cut, NEG) and CutSpace(cut, POS) of the measure's cut")
            raise ValueError(f"interface_nitsche: fields=(f_NEG, f_POS) must name the NEG field, then the POS field, of "
                             f"the measure's cut; got {where}: {fix}")
        return {"neg_field": k[0], "pos_field": k[1]}

    def coupling(u, v, w):
        i_neg, i_pos = w.neg_field, w.pos_field
        kn, kp, penalty = k_neg[w.parent][:, None], k_pos[w.parent][:, None], (w.gamma * two_s[w.parent])[:, None] / w.h
        un, up, vn, vp = u[i_neg], u[i_pos], v[i_neg], v[i_pos]
        flux_u = kn * a_neg * dot(w.n, un.grad) + kp * a_pos * dot(w.n, up.grad)
        flux_v = kn * a_neg * dot(w.n, vn.grad) + kp * a_pos * dot(w.n, vp.grad)
        ju, jv = un - up, vn - vp
        return -flux_u * jv - flux_v * ju + penalty * ju * jv

    integrand = Integrand(coupling, False, symmetric=True, prepare=prepare, advice=_nitsche_advice, high_order=lambda term, W, offsets:
                          high_order.interface_blocks(term, W, offsets, prepare(W, term), k_neg, a_neg, a_pos, two_s), fields=True)
    return Form([(1.0, Term(integrand, measure, None, {"gamma": gamma}))], False)


# ---------------------------------------------------------------------------------------------
# strong conditions
# ---------------------------------------------------------------------------------------------


def apply_dirichlet(K, b, dofs, values):
    """Strong Dirichlet conditions u[dofs] = values, by symmetric elimination in place of the rows.

    Returns ``(K_bc, b_bc)`` of the same size: the rows and columns of ``dofs`` are replaced by
    d_i e_i^T (d_i = |K_ii|, or 1 where K_ii = 0), b_bc = b - K[:, dofs] g outside ``dofs`` and
    b_bc = d_i g_i on them.  K_bc stays symmetric (positive definite when K is on the other dofs),
    its solution carries the prescribed values, and the dof numbering (hence a multigrid hierarchy)
    is unchanged.  Why d_i and not 1: an iterative solver stops on |b - K x| <= tol |b|, and unit
    rows make the Dirichlet values part of |b| at their own scale, unrelated to K's.  With a small
    coefficient (the interface problem at a_POS = 1e-3, where g ~ 1 / a_POS and K ~ a_POS) the
    values dwarfed the interior equations and CG stopped with those unsolved (inside L2 error 0.27
    against 0.087 at spacing 0.05); rows at K's own scale keep every equation weighed alike.

    ``dofs``: integer dof numbers in [0, n), in any order (``values[i]`` goes with ``dofs[i]``; a dof
    given twice must have the same value twice), or a boolean mask of length n, which stands for
    ``np.flatnonzero(mask)`` (the values then go with the masked dofs in increasing order).
    ``values``: a number (every dof, every column), or one row per dof, shape (len(dofs),) + b.shape[1:]
    (b is (n,) or (n, c)); real and finite.  Anything else is refused with the shapes."""
    K = sp.csr_matrix(K)
    n = K.shape[0]
    if K.shape != (n, n):
        raise ValueError(f"K must be square, got shape {K.shape}")
    b = np.asarray(b, dtype=float)
    if b.ndim not in (1, 2) or len(b) != n:
        raise ValueError(f"b must have shape ({n},) or ({n}, c) for K of shape {K.shape}, got {b.shape}")
    dofs = np.asarray(dofs)
    if dofs.dtype == bool:
        if dofs.shape != (n,):
            raise ValueError(f"a boolean mask of Dirichlet dofs must have shape ({n},), got {dofs.shape}")
        dofs = np.flatnonzero(dofs)
    elif dofs.size == 0:
        dofs = np.zeros(0, dtype=np.int64)
    elif dofs.dtype.kind not in "iu":
        raise TypeError(f"Dirichlet dofs must be integer dof numbers (or a boolean mask of length {n}), got {dofs.dtype} values")
    if dofs.ndim != 1:
        raise ValueError(f"Dirichlet dofs must be a 1-d array of dof numbers, got shape {dofs.shape}")
    if dofs.size and (dofs.min() < 0 or dofs.max() >= n):
        raise ValueError(f"Dirichlet dofs must lie in [0, {n})")
    rows = (dofs.size,) + b.shape[1:]
    values = np.asarray(values)
    if values.dtype.kind not in "biuf":
        raise TypeError(f"Dirichlet values must be real numbers, got {values.dtype} values")
    values = np.broadcast_to(values.astype(float), rows) if values.ndim == 0 else values.astype(float)
    if values.shape != rows:
        raise ValueError(f"Dirichlet values must be a number or have shape {rows} (one row per dof of dofs, "
                         f"{dofs.size} of them), got {values.shape}")
    if not np.all(np.isfinite(values)):
        raise ValueError("Dirichlet values must be finite (no nan or inf)")
    dofs, first, which = np.unique(dofs, return_index=True, return_inverse=True)
    g_dofs = values[first]  # the values in the order of the sorted dofs: each stays with its dof
    if len(dofs) < len(which):
        differ = np.flatnonzero(np.any((values != g_dofs[which]).reshape(len(which), -1), axis=1))
        if differ.size:
            d = dofs[which[differ[0]]]
            raise ValueError(f"Dirichlet dof {d} is given twice with different values, {g_dofs[which[differ[0]]]} and "
                             f"{values[differ[0]]}")
    g = np.zeros((n,) + b.shape[1:])
    g[dofs] = g_dofs
    keep = np.ones(n)
    keep[dofs] = 0.0
    scale = np.zeros(n)
    diagonal = np.abs(K.diagonal()[dofs])
    scale[dofs] = np.where(diagonal > 0, diagonal, 1.0)  # the rows of the eliminated dofs: d_i e_i^T
    D = sp.diags(keep)
    column = (n,) + (1,) * (b.ndim - 1)
    b_bc = keep.reshape(column) * (b - K @ g) + scale.reshape(column) * g
    K_bc = (D @ K @ D + sp.diags(scale)).tocsr()
    return K_bc, b_bc


# ---------------------------------------------------------------------------------------------
# checks of the parameters
# ---------------------------------------------------------------------------------------------


def _h_power(h: np.ndarray, a: float, what: str) -> np.ndarray:
    """h^a of the local sizes h (> 0), or a ValueError naming ``what`` when some h^a is not a finite
    positive float64: a power that overflows (h^a = inf, a matrix of inf and NaN) or underflows
    (h^a = 0, the term silently gone) for the sizes of this mesh."""
    with np.errstate(over="ignore", under="ignore"):
        s = h**a
    if not (np.all(np.isfinite(s)) and np.all(s > 0)):
        raise ValueError(f"{what}: h^a with a = h_power = {a!r} is not a finite positive number for the local h in "
                         f"[{h.min():.3g}, {h.max():.3g}] (it overflows or underflows in float64); choose a power a for "
                         "which h^a is finite and nonzero")
    return s


def _positive(**values):
    """Each keyword a real, finite, positive number, or an error naming it: a TypeError for what is
    not one real number (:func:`~cutfem.fem.forms._number`), a ValueError for nan, inf, zero and
    negative numbers."""
    for name, value in values.items():
        try:
            ok = _number(name, value) > 0
        except ValueError:
            ok = False
        if not ok:
            raise ValueError(f"{name} must be a positive number, got {value!r}")
