"""Tests for cutfem.fem.terms: identities of the built-in surface terms, stabilizations and loads.

Expected numbers come from exact identities and formulas written here:

* sum of the mass matrix = |S_h|; A 1 = 0; sum_k x_k^T A x_k = int_{S_h} tr P_h = 2 |S_h|;
* jumps of globally linear functions vanish across flat edges and across every face; on a unit
  cube triangulated arbitrarily within its faces, J_E(u, u) = 8 h |g|^2 for u = g . x (only the
  12 creases contribute: (g . (n_1 + n_2))^2 per unit length, summed over the sign patterns);
* the cut P1 trace space always contains phi_h, which vanishes on S_h: M phi = A phi = 0.
|S_h| is summed from the triangles' cross products in the test.
"""

import warnings

import numpy as np
import pytest

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.forms import assemble, bilinear_form, linear_form
from cutfem.fem.pointwise import dot
from cutfem.fem.terms import (
    basis_integrals,
    edge_jump_penalty,
    face_jump_penalty,
    interface_nitsche,
    load,
    mass,
    nitsche,
    normal_gradient_penalty,
    position_load,
    stiffness,
    tangential_stiffness,
)
from cutfem.geometry.shapes import Sphere, Torus
from cutfem.geometry.markers import CUT, NEG, POS
from cutfem.solvers.diagnose import SolverError
from cutfem.solvers.solve import solve
from cutfem.geometry.box import structured_box
from cutfem.geometry.mesh import unstructured_box
from cutfem.fem.spaces import CutSpace, SurfaceP1Space
from cutfem.geometry.surface import SurfaceMesh
from cutfem.geometry.surface_meshes import sphere_mesh, torus_mesh
from cutfem.geometry.measures import surface_measure as ds
from surface_matrices import dF, edge_matrix, face_matrix, load_vector, mass_matrix, stiffness_matrix


SMOOTH = lambda x: np.sin(x[..., 0]) * np.exp(x[..., 1] / 2)  # noqa: E731


def triangles_area(P):
    """Total area of triangles P (m, 3, 3)."""
    return 0.5 * np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1).sum()


def surface_triangles(V):
    """Vertex coordinates (m, 3, 3) of the triangles of S_h of a meshed or cut space."""
    if isinstance(V, SurfaceP1Space):
        return np.asarray(V.dof_points)[V.element_dofs]
    return V.cut.vertices[V.cut.triangles]


SPACES = {
    "meshed-sphere": lambda: SurfaceP1Space(sphere_mesh(3, radius=0.8)),
    "meshed-torus": lambda: SurfaceP1Space(torus_mesh(24, "perturbed-flipped", seed=5)),
    "cut-sphere": lambda: CutSpace(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=16), Sphere(0.7, [0.03, -0.01, 0.02]))),
    "cut-torus": lambda: CutSpace(cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.1), Torus())),
}

# small spaces for dense eigenvalue computations (a few hundred unknowns)
SMALL = {
    "meshed-sphere": lambda: SurfaceP1Space(sphere_mesh(2, radius=0.8)),
    "meshed-torus": lambda: SurfaceP1Space(torus_mesh(16, "perturbed-flipped", seed=6)),
    "cut-sphere": lambda: CutSpace(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=8), Sphere(0.7, [0.03, -0.01, 0.02]))),
    "cut-torus": lambda: CutSpace(cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.4), Torus(1.0, 0.5))),
}


@pytest.fixture(scope="module", params=sorted(SPACES))
def space(request):
    return SPACES[request.param]()


@pytest.fixture(scope="module", params=sorted(SMALL))
def small_space(request):
    return SMALL[request.param]()


@pytest.fixture(scope="module")
def small_cut_spaces():
    return [SMALL["cut-sphere"](), SMALL["cut-torus"]()]


def relative_norm(x, scale):
    return np.abs(x).max() / scale



# ----------------------------------------------------------------------------------------------
# mass and tangential stiffness
# ----------------------------------------------------------------------------------------------


def test_mass_sums_to_area(space):
    area = triangles_area(surface_triangles(space))
    M = mass_matrix(space)
    assert M.sum() == pytest.approx(area, rel=1e-12)
    assert mass_matrix(space).sum() == pytest.approx(area, rel=1e-12)
    one = np.ones(space.n_dofs)
    assert one @ M @ one == pytest.approx(area, rel=1e-12)


def test_basis_integrals_are_the_column_sums_of_the_mass(space):
    """int phi_i = (1^T M)_i on S_h (per piece on a cut, closed form on a mesh), without M."""
    ones = assemble(basis_integrals(ds(space)), space)
    M = mass_matrix(space)
    assert ones.shape == (space.n_dofs,)
    np.testing.assert_allclose(ones, np.asarray(M.sum(axis=0)).ravel(), rtol=0, atol=1e-13 * ones.max())
    assert ones.sum() == pytest.approx(triangles_area(surface_triangles(space)), rel=1e-12)


def test_basis_integrals_over_a_side_and_refusals():
    cut = cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=8), Sphere(0.7, [0.03, -0.01, 0.02]))
    V = CutSpace(cut, NEG)
    ones = assemble(basis_integrals(cut.dx(NEG)), V)  # quadrature of degree 1: exact for P1
    np.testing.assert_allclose(ones, np.asarray(assemble(mass(cut.dx(NEG)), V).sum(axis=0)).ravel(), rtol=0, atol=1e-14)
    with pytest.raises(TypeError, match="facets"):
        basis_integrals(cut.dF(cut.ghost_facets(NEG)))


def test_lattice_terms_of_a_form_sum_into_one_matrix():
    """The terms of a form that sum into lattice slots (piece mass, face penalty, volume mass and
    stiffness of whole tets) go into one set of slots, each times its coefficient (negative ones
    too): the matrix of the sum is the sum of the matrices, to round-off, and exactly symmetric."""
    cut = cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.1), Torus())
    V = CutSpace(cut)
    J = face_jump_penalty(dF(V))
    A = assemble(mass(cut.ds()) + 0.3 * J, V)
    B = assemble(mass(cut.ds()), V) + 0.3 * assemble(J, V)
    assert abs(A - B).max() <= 1e-15 * abs(B).max()
    assert (A - A.T).nnz == 0
    W = CutSpace(cut, NEG)
    G = face_jump_penalty(cut.dF(cut.ghost_facets(NEG)), h_power=1)
    A = assemble(stiffness(cut.dx(NEG)) - 2.0 * mass(cut.dx(NEG)) + 0.1 * G, W)
    B = assemble(stiffness(cut.dx(NEG)), W) - 2.0 * assemble(mass(cut.dx(NEG)), W) + 0.1 * assemble(G, W)
    assert abs(A - B).max() <= 1e-14 * abs(B).max()
    assert abs(A - A.T).max() <= 1e-15 * abs(B).max()  # the cut cells' mass is a Gram product


@pytest.mark.parametrize("which", ["cut-sphere", "cut-torus"])
def test_cut_mass_by_piece_moments_equals_triangle_route(which):
    """The moment route of the cut mass (three rows per tet) against the per-triangle formula
    Lambda^T |T|/12 (I + 1 1^T) Lambda, and exactly symmetric; x^T M x = int |x|^2 on S_h."""
    from cutfem.fem.closed_forms import _simplex_mass

    space = SPACES[which]()
    M = mass_matrix(space)
    reference = _simplex_mass(space, *space.surface_triangles())
    assert relative_norm((M - reference).data, np.abs(reference).max()) < 1e-12
    assert (M - M.T).nnz == 0
    X = space.interpolate(lambda x: x)
    P = surface_triangles(space)
    # int_T |x|^2 exactly for linear x: |T|/12 (sum_v |x_v|^2 + |sum_v x_v|^2)
    areas = 0.5 * np.linalg.norm(np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]), axis=1)
    exact = (areas / 12 * (np.einsum("tvd,tvd->t", P, P) + np.einsum("td,td->t", P.sum(1), P.sum(1)))).sum()
    assert np.einsum("ik,ik->", X, M @ X) == pytest.approx(exact, rel=1e-12)


def test_tangential_stiffness_identities(space):
    A = stiffness_matrix(space)
    scale = np.abs(A).max()
    assert relative_norm(A @ np.ones(space.n_dofs), scale) < 1e-12  # constants are annihilated
    X = space.interpolate(lambda x: x)
    trace = np.einsum("ik,ik->", X, A @ X)  # sum over the coordinate functions
    assert trace == pytest.approx(2 * triangles_area(surface_triangles(space)), rel=1e-11)


def test_position_load_is_stiffness_times_coordinates(space):
    """b = A x without A: the same vector to round-off, columns summing to zero (closed surface),
    and x^T b = sum_k x_k^T A x_k = 2 |S_h|."""
    B = assemble(position_load(ds(space)), space)
    X = space.interpolate(lambda x: x)
    AX = stiffness_matrix(space) @ X
    scale = np.abs(AX).max()
    assert B.shape == (space.n_dofs, 3)
    assert relative_norm(B - AX, scale) < 1e-12
    assert np.abs(B.sum(axis=0)).max() < 1e-13 * np.abs(B).sum()  # round-off of a sum of n terms
    assert np.einsum("ik,ik->", X, B) == pytest.approx(2 * triangles_area(surface_triangles(space)), rel=1e-11)


def test_position_load_refuses_a_volume_space():
    cut = cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=4), Sphere(0.7))
    V = CutSpace(cut, NEG)
    with pytest.raises(TypeError, match="SurfacePieces or MeshedSurface"):
        position_load(cut.dx(NEG))
    with pytest.raises(ValueError, match="needs the field on the cut tets"):
        assemble(position_load(cut.ds()), V)


# ----------------------------------------------------------------------------------------------
# stabilizations: symmetry, semi-definiteness, consistency on linear functions
# ----------------------------------------------------------------------------------------------


def test_jump_penalties_exactly_symmetric_and_semidefinite(small_space):
    V = small_space
    mats = [edge_matrix(V)] + ([face_matrix(V)] if isinstance(V, CutSpace) else [])
    for J in mats:
        assert (J - J.T).nnz == 0  # bitwise symmetric
        ev = np.linalg.eigvalsh(J.toarray())
        assert ev[-1] > 0
        assert ev[0] >= -1e-12 * ev[-1]


def cube_mesh(n, seed):
    """The unit cube's surface, an n x n grid on each face, each cell split along a random
    diagonal, the nodes inside the faces moved at random within their face (all faces stay flat)."""
    rng = np.random.default_rng(seed)
    index = {}
    points = []

    def node(ijk):
        if ijk not in index:
            index[ijk] = len(points)
            points.append(np.array(ijk, float))
        return index[ijk]

    triangles = []
    for axis in range(3):
        b, c = (axis + 1) % 3, (axis + 2) % 3  # e_b x e_c = e_axis
        for side in (0, n):
            for p in range(n):
                for q in range(n):
                    corners = []
                    for dp, dq in ((0, 0), (1, 0), (1, 1), (0, 1)):  # counter-clockwise seen along +e_axis
                        ijk = [0, 0, 0]
                        ijk[axis], ijk[b], ijk[c] = side, p + dp, q + dq
                        corners.append(node(tuple(ijk)))
                    v0, v1, v2, v3 = corners
                    cell = [[v0, v1, v2], [v0, v2, v3]] if rng.random() < 0.5 else [[v0, v1, v3], [v1, v2, v3]]
                    if side == 0:  # outward normal -e_axis
                        cell = [[t[0], t[2], t[1]] for t in cell]
                    triangles += cell
    P = np.array(points)
    on_side = (P == 0) | (P == n)
    inner = on_side.sum(axis=1) == 1  # strictly inside one face
    move = rng.uniform(-0.3, 0.3, size=P.shape) * ~on_side
    P[inner] += move[inner]
    return SurfaceMesh(P / n, np.array(triangles))


@pytest.mark.parametrize("seed", [0, 1])
def test_edge_jump_on_flat_faces_only_creases_count(seed):
    mesh = cube_mesh(5, seed)
    assert mesh.flipped_components == 0 and mesh.euler_characteristic == 2
    V = SurfaceP1Space(mesh)
    J = edge_matrix(V)
    g = np.array([0.4, -1.1, 0.7])
    u = V.interpolate(lambda x: x @ g)
    # the flat faces contribute nothing, each crease its exact share (nonzero: the check can fail)
    assert u @ J @ u == pytest.approx(8 * V.h * g @ g, rel=1e-11)
    assert relative_norm(J @ np.ones(V.n_dofs), np.abs(J).max()) < 1e-12  # constants: no jump anywhere


def test_edge_jump_vanishes_on_linear_functions_on_a_cut_plane():
    normal = np.array([0.3, -0.2, 1.0]) / np.linalg.norm([0.3, -0.2, 1.0])
    box = structured_box([-1, -1, -1], [1, 1, 1], cells=8)
    with warnings.catch_warnings():  # the plane's border edges (on the box) have one piece only
        warnings.simplefilter("ignore", RuntimeWarning)
        V = CutSpace(cut_mesh(box, lambda x: x @ normal - 0.137, check_boundary=False))
        J = edge_matrix(V)
    assert J.nnz > 0
    g = np.array([0.7, -1.3, 0.4])
    u = V.interpolate(lambda x: x @ g)
    scale = np.abs(J).max() * np.abs(u).max()
    assert relative_norm(J @ u, scale) < 1e-12
    quadratic = V.interpolate(lambda x: (x**2).sum(axis=-1))
    assert quadratic @ J @ quadratic > 1e-3 * np.abs(J).max()  # the check can fail


@pytest.fixture(scope="module")
def unstructured_cut_space():
    bg = unstructured_box([-1, -1, -1], [1, 1, 1], edge_length=0.4)
    return CutSpace(cut_mesh(bg, Sphere(0.65, [0.02, 0.03, -0.01])))


@pytest.mark.parametrize("which", ["cut-sphere", "cut-torus", "unstructured"])
def test_face_jump_vanishes_on_linear_functions(which, unstructured_cut_space):
    V = unstructured_cut_space if which == "unstructured" else SPACES[which]()
    J = face_matrix(V)
    g = np.array([1.3, 0.2, -0.8])
    u = V.interpolate(lambda x: x @ g + 0.5)
    scale = np.abs(J).max() * np.abs(u).max()
    assert relative_norm(J @ u, scale) < 1e-12
    assert relative_norm(face_matrix(V, h_power=1.0) @ u, scale * V.h) < 1e-12
    quadratic = V.interpolate(lambda x: (x**2).sum(axis=-1))
    assert quadratic @ J @ quadratic > 1e-3 * np.abs(J).max()  # the check can fail


def test_cut_trace_space_contains_the_level_set():
    """phi_h vanishes on S_h, so its nodal vector is in the kernel of the unstabilized cut mass and
    stiffness matrices (the cut system is singular without stabilization); J_F(phi_h, phi_h) > 0
    on a curved surface."""
    V = SPACES["cut-sphere"]()
    phi = V.cut.values
    M, A, J = mass_matrix(V), stiffness_matrix(V), face_matrix(V)
    assert relative_norm(M @ phi, np.abs(M).max() * np.abs(phi).max()) < 1e-12
    assert relative_norm(A @ phi, np.abs(A).max() * np.abs(phi).max()) < 1e-12
    assert phi @ J @ phi > 1e-3 * np.abs(J).max() * np.abs(phi).max() ** 2


def test_stabilized_cut_mass_is_positive_definite(small_cut_spaces):
    for V in small_cut_spaces:
        M, J = mass_matrix(V), face_matrix(V)
        for tau in (0.1, 1e-3):
            ev = np.linalg.eigvalsh((M + tau * J).toarray())
            assert ev[0] > 1e-9 * ev[-1]
        assert np.linalg.eigvalsh(M.toarray())[0] < 1e-13 * np.abs(M).max()  # unstabilized: singular


def test_flat_cut_is_not_stabilized_by_face_jumps():
    """On a plane phi_h is globally linear: J_F(phi_h) = 0 as well, so M + tau J_F stays singular.
    (The positive definiteness above needs a surface that is not flat.)"""
    box = structured_box([-1, -1, -1], [1, 1, 1], cells=6)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        V = CutSpace(cut_mesh(box, lambda x: x[..., 2] - 0.3 * x[..., 0] - 0.11, check_boundary=False))
    S = assemble(mass(ds(V)) + 0.1 * face_jump_penalty(dF(V)), V)
    phi = V.dof_points[:, 2] - 0.3 * V.dof_points[:, 0] - 0.11
    assert relative_norm(S @ phi, np.abs(S).max() * np.abs(phi).max()) < 1e-12




# ----------------------------------------------------------------------------------------------
# load vectors and linear forms
# ----------------------------------------------------------------------------------------------


def test_load_constant_vector_and_linear(space):
    area = triangles_area(surface_triangles(space))
    b = load_vector(space, lambda x: np.full(x.shape[:2], 2.5))
    assert b.shape == (space.n_dofs,) and b.sum() == pytest.approx(2.5 * area, rel=1e-12)
    c = np.array([1.0, -2.0, 0.5])
    B = load_vector(space, lambda x: np.broadcast_to(c, x.shape))
    assert B.shape == (space.n_dofs, 3)
    np.testing.assert_allclose(B.sum(axis=0), c * area, rtol=1e-12)
    # a linear f lies in V_h: (f, phi_i) = (M f_nodes)_i exactly
    g = np.array([0.3, 0.9, -0.4])
    f = load_vector(space, lambda x: x @ g + 1.0, degree=2)
    expected = mass_matrix(space) @ space.interpolate(lambda x: x @ g + 1.0)
    np.testing.assert_allclose(f, expected, rtol=0, atol=1e-13 * np.abs(expected).max())


def test_load_with_closest_point_and_bad_shape():
    V = SPACES["cut-sphere"]()
    c = np.array([0.03, -0.01, 0.02])
    sphere = Sphere(0.7, c)

    def f(x):  # f(x) = (x - c)_z restricted to the sphere, i.e. 0.7 times the unit direction's z
        return x[..., 2] - c[2]

    def radial(x):  # f o p for the closest point p(x) = c + 0.7 (x - c) / |x - c|
        d = x - c
        return 0.7 * d[..., 2] / np.linalg.norm(d, axis=-1)

    np.testing.assert_allclose(load_vector(V, f, closest_point=sphere.closest_point), load_vector(V, radial), rtol=1e-12, atol=1e-15)
    with pytest.raises(ValueError, match="shape"):
        load_vector(V, lambda x: np.zeros(len(x)))


# ----------------------------------------------------------------------------------------------
# one home per parameter: the Nitsche term carries gamma to its matrix, its load and the advice
# ----------------------------------------------------------------------------------------------



@pytest.fixture(scope="module")
def ball_cut():
    return cut_mesh(structured_box([-1.1] * 3, [1.1] * 3, spacing=0.3), Sphere(0.8, [0.03, -0.01, 0.02]))


def _nitsche_reference(sign, gamma):
    """The symmetric Nitsche matrix and load of u = g written out here as integrands, with the outward
    normal sign * n_h of the field's side: -(n.grad u, v) - (u, n.grad v) + gamma/h (u, v) and
    (g, gamma/h v - n.grad v)."""

    @bilinear_form(symmetric=True)
    def matrix(u, v, w):
        n = sign * w.n
        return -dot(n, u.grad) * v.value - dot(n, v.grad) * u.value + (gamma / w.h) * u.value * v.value

    @linear_form
    def rhs(v, w):
        g = w.at(w.data)
        return g * ((gamma / w.h) * v.value - dot(sign * w.n, v.grad))

    return matrix, rhs


@pytest.mark.parametrize("side, sign", [(NEG, 1.0), (POS, -1.0)])
@pytest.mark.parametrize("gamma", [10.0, 3.7])
def test_nitsche_term_carries_gamma_to_its_matrix_and_load(ball_cut, side, sign, gamma):
    """N = nitsche(ds, gamma, g=...): its matrix and N.load are the integrands of the formula with that
    gamma (to round-off), so gamma is given once for both."""
    V, ds_ = CutSpace(ball_cut, side), ball_cut.ds()
    N = nitsche(ds_, gamma, g=SMOOTH)
    matrix, rhs = _nitsche_reference(sign, gamma)
    K, K_ref = assemble(N, V), assemble(matrix * ds_, V)
    assert abs(K - K_ref).max() <= 1e-12 * abs(K_ref).max()
    b, b_ref = assemble(N.load, V), assemble(rhs * ds_, V, data=SMOOTH)
    assert np.abs(b - b_ref).max() <= 1e-12 * np.abs(b_ref).max()
    # the load follows the term's gamma: another gamma, another vector
    other = assemble(nitsche(ds_, 2 * gamma, g=SMOOTH).load, V)
    assert np.abs(other - b).max() > 1e-3 * np.abs(b).max()


def test_indefinite_hint_comes_from_the_terms(ball_cut):
    ds_, ghost = ball_cut.ds(), face_jump_penalty(ball_cut.dF(ball_cut.ghost_facets(NEG)), h_power=1)
    dx = ball_cut.dx(NEG)
    N = nitsche(ds_, 2.5, g=SMOOTH)
    alone = (stiffness(dx) + N).indefinite_hint
    assert alone.startswith("raise the Nitsche penalty (gamma 2.5 is below its stability bound)")
    assert "add a ghost penalty (the form has none" in alone
    assert (stiffness(dx) + N + 0.0 * ghost).indefinite_hint == alone  # a zero coefficient adds no ghost penalty
    assert (stiffness(dx) + N + 0.1 * ghost).indefinite_hint == "raise the Nitsche penalty (gamma 2.5 is below its stability bound)"
    assert (stiffness(dx) + 0.1 * ghost).indefinite_hint is None
    assert "gamma 3 is below" in interface_nitsche(ds_, 1.0, 2.0, gamma=3.0).indefinite_hint


@pytest.mark.parametrize("ghost", [False, True])
def test_indefinite_system_error_names_the_nitsche_penalty(ghost):
    """gamma = 0.5 is below the stability bound: the solver refuses the system with the advice of its
    form, which names gamma's value and, without a ghost penalty, the ghost penalty it lacks."""
    cut = cut_mesh(structured_box([-1.1] * 3, [1.1] * 3, spacing=0.1), Sphere(1.0))
    V, dx, ds_ = CutSpace(cut, NEG), cut.dx(NEG), cut.ds()
    N = nitsche(ds_, 0.5, g=SMOOTH)
    a = stiffness(dx) + N
    if ghost:
        a = a + 0.1 * face_jump_penalty(cut.dF(cut.ghost_facets(NEG)), h_power=1)
    K, b = assemble(a, V), assemble(load(lambda x: 0.75 * SMOOTH(x), dx) + N.load, V)
    with pytest.raises(SolverError, match=r"raise the Nitsche penalty \(gamma 0.5 is below its stability bound\)") as err:
        solve(K, b, method="direct", indefinite_hint=a.indefinite_hint)
    assert err.value.cause == "indefinite"
    assert ("add a ghost penalty" in str(err.value)) is not ghost


# ----------------------------------------------------------------------------------------------
# the built-in terms are integrands: their exact implementations are their quadrature to round-off
# ----------------------------------------------------------------------------------------------


def _built_in_cases(cut, mesh_space):
    trace, bulk, outer = CutSpace(cut, CUT), CutSpace(cut, NEG), CutSpace(cut, POS)
    interior, ghost = cut.dF(cut.interior_facets(CUT)), cut.dF(cut.ghost_facets(NEG))
    dS = mesh_space.mesh.ds()
    return {
        "mass S_h": (mass(cut.ds()), trace),
        "mass S_h, bulk field": (mass(cut.ds()), bulk),
        "mass Omega_h": (mass(cut.dx(NEG)), bulk),
        "mass cut tets": (mass(cut.dx(CUT)), trace),
        "mass meshed": (mass(dS), mesh_space),
        "stiffness": (stiffness(cut.dx(NEG)), bulk),
        "tangential_stiffness": (tangential_stiffness(cut.ds()), trace),
        "tangential_stiffness meshed": (tangential_stiffness(dS), mesh_space),
        "face_jump_penalty J_F": (face_jump_penalty(interior), trace),
        "face_jump_penalty ghost": (face_jump_penalty(ghost, h_power=1), bulk),
        "normal_gradient_penalty": (normal_gradient_penalty(cut.dx(CUT), h_power=-1), trace),
        "nitsche NEG": (nitsche(cut.ds(), 7.0), bulk),
        "nitsche POS": (nitsche(cut.ds(), 7.0), outer),
        "nitsche load POS": (nitsche(cut.ds(), 7.0, g=SMOOTH).load, outer),
        "load": (load(SMOOTH, cut.dx(NEG)), bulk),
        "position_load": (position_load(cut.ds()), trace),
        "position_load meshed": (position_load(dS), mesh_space),
        "basis_integrals": (basis_integrals(cut.ds()), trace),
        "basis_integrals meshed": (basis_integrals(dS), mesh_space),
    }


CASES = [
    "mass S_h", "mass S_h, bulk field", "mass Omega_h", "mass cut tets", "mass meshed", "stiffness", "tangential_stiffness",
    "tangential_stiffness meshed", "face_jump_penalty J_F", "face_jump_penalty ghost", "normal_gradient_penalty",
    "nitsche NEG", "nitsche POS", "nitsche load POS", "load", "position_load", "position_load meshed", "basis_integrals",
    "basis_integrals meshed"]


@pytest.fixture(scope="module")
def built_ins(ball_cut):
    return _built_in_cases(ball_cut, SurfaceP1Space(torus_mesh(12, "perturbed-flipped", seed=3)))


@pytest.mark.parametrize("case", CASES)
def test_exact_implementation_is_the_quadrature_of_the_integrand(built_ins, case):
    form, V = built_ins[case]
    exact, quadrature = assemble(form, V), assemble(form.by_quadrature(), V)
    if form.linear:
        assert np.abs(exact - quadrature).max() <= 1e-12 * np.abs(quadrature).max()
    else:
        assert abs(exact - quadrature).max() <= 1e-12 * abs(quadrature).max()
        assert abs(quadrature).max() > 0


def test_scaled_sums_of_built_in_terms_are_their_quadrature(built_ins, ball_cut):
    """c_1 a_1 + c_2 a_2 of built-in terms (one running sum) against the same form by quadrature."""
    V = CutSpace(ball_cut, CUT)
    form = 2.5 * mass(ball_cut.ds()) - 0.3 * tangential_stiffness(ball_cut.ds()) + 0.1 * face_jump_penalty(ball_cut.dF(ball_cut.interior_facets(CUT)))
    exact, quadrature = assemble(form, V), assemble(form.by_quadrature(), V)
    assert abs(exact - quadrature).max() <= 1e-12 * abs(quadrature).max()


def test_edge_penalty_has_no_quadrature_route(ball_cut):
    with pytest.raises(TypeError, match="no quadrature measure covers"):
        assemble(edge_jump_penalty(ball_cut.ds()).by_quadrature(), CutSpace(ball_cut, CUT))
