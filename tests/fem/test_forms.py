"""Tests for cutfem.fem.forms: identities of the surface forms and stabilizations, user forms, loads.

Expected numbers come from exact identities and formulas written here:

* sum of the mass matrix = |S_h|; A 1 = 0; sum_k x_k^T A x_k = int_{S_h} tr P_h = 2 |S_h|;
* jumps of globally linear functions vanish across flat edges and across every face; on a unit
  cube triangulated arbitrarily within its faces, J_E(u, u) = 8 h |g|^2 for u = g . x (only the
  12 creases contribute: (g . (n_1 + n_2))^2 per unit length, summed over the sign patterns);
* the cut P1 trace space always contains phi_h, which vanishes on S_h: M phi = A phi = 0;
* exact P1 product formulas for the advection reference.
|S_h| is summed from the triangles' cross products in the test.
"""

import warnings

import numpy as np
import pytest
import scipy.sparse as sp

from cutfem.geometry.cut import cut_mesh
from cutfem.fem.forms import assemble, bilinear_form, linear_form
from cutfem.fem.pointwise import dot
from cutfem.fem.terms import basis_integrals, face_jump_penalty, mass, position_load, stiffness
from cutfem.geometry.levelset import Sphere, Torus
from cutfem.geometry.markers import NEG
from cutfem.geometry.mesh import structured_box, unstructured_box
from cutfem.fem.spaces import CutP1Space, SurfaceP1Space
from cutfem.geometry.surface import SurfaceMesh, sphere_mesh, torus_mesh
from cutfem.geometry.measures import surface_measure as ds
from surface_matrices import dF, edge_matrix, face_matrix, load_vector, mass_matrix, stiffness_matrix


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
    "cut-sphere": lambda: CutP1Space(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=16), Sphere(0.7, [0.03, -0.01, 0.02]))),
    "cut-torus": lambda: CutP1Space(cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.1), Torus())),
}

# small spaces for dense eigenvalue computations (a few hundred unknowns)
SMALL = {
    "meshed-sphere": lambda: SurfaceP1Space(sphere_mesh(2, radius=0.8)),
    "meshed-torus": lambda: SurfaceP1Space(torus_mesh(16, "perturbed-flipped", seed=6)),
    "cut-sphere": lambda: CutP1Space(cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=8), Sphere(0.7, [0.03, -0.01, 0.02]))),
    "cut-torus": lambda: CutP1Space(cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.4), Torus(1.0, 0.5))),
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
    V = CutP1Space(cut, NEG)
    ones = assemble(basis_integrals(cut.dx(NEG)), V)  # quadrature of degree 1: exact for P1
    np.testing.assert_allclose(ones, np.asarray(assemble(mass(cut.dx(NEG)), V).sum(axis=0)).ravel(), rtol=0, atol=1e-14)
    with pytest.raises(TypeError, match="facets"):
        basis_integrals(cut.dF(cut.ghost_facets(NEG)))


def test_lattice_terms_of_a_form_sum_into_one_matrix():
    """The terms of a form that sum into lattice slots (piece mass, face penalty, volume mass and
    stiffness of whole tets) go into one set of slots, each times its coefficient (negative ones
    too): the matrix of the sum is the sum of the matrices, to round-off, and exactly symmetric."""
    cut = cut_mesh(structured_box([-1.6, -1.6, -0.6], [1.6, 1.6, 0.6], spacing=0.1), Torus())
    V = CutP1Space(cut)
    J = face_jump_penalty(dF(V))
    A = assemble(mass(cut.ds()) + 0.3 * J, V)
    B = assemble(mass(cut.ds()), V) + 0.3 * assemble(J, V)
    assert abs(A - B).max() <= 1e-15 * abs(B).max()
    assert (A - A.T).nnz == 0
    W = CutP1Space(cut, NEG)
    G = face_jump_penalty(cut.dF(cut.ghost_facets(NEG)), h_power=1)
    A = assemble(stiffness(cut.dx(NEG)) - 2.0 * mass(cut.dx(NEG)) + 0.1 * G, W)
    B = assemble(stiffness(cut.dx(NEG)), W) - 2.0 * assemble(mass(cut.dx(NEG)), W) + 0.1 * assemble(G, W)
    assert abs(A - B).max() <= 1e-14 * abs(B).max()
    assert abs(A - A.T).max() <= 1e-15 * abs(B).max()  # the cut cells' mass is a Gram product


@pytest.mark.parametrize("which", ["cut-sphere", "cut-torus"])
def test_cut_mass_by_piece_moments_equals_triangle_route(which):
    """The moment route of the cut mass (three rows per tet) against the per-triangle formula
    Lambda^T |T|/12 (I + 1 1^T) Lambda, and exactly symmetric; x^T M x = int |x|^2 on S_h."""
    from cutfem.fem.exact import _simplex_mass

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
    V = CutP1Space(cut, NEG)
    with pytest.raises(TypeError, match="SurfacePieces or MeshedSurface"):
        position_load(cut.dx(NEG))
    with pytest.raises(ValueError, match="needs the field on the cut tets"):
        assemble(position_load(cut.ds()), V)


# ----------------------------------------------------------------------------------------------
# stabilizations: symmetry, semi-definiteness, consistency on linear functions
# ----------------------------------------------------------------------------------------------


def test_jump_penalties_exactly_symmetric_and_semidefinite(small_space):
    V = small_space
    mats = [edge_matrix(V)] + ([face_matrix(V)] if isinstance(V, CutP1Space) else [])
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
        V = CutP1Space(cut_mesh(box, lambda x: x @ normal - 0.137, check_boundary=False))
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
    return CutP1Space(cut_mesh(bg, Sphere(0.65, [0.02, 0.03, -0.01])))


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
        V = CutP1Space(cut_mesh(box, lambda x: x[..., 2] - 0.3 * x[..., 0] - 0.11, check_boundary=False))
    S = assemble(mass(ds(V)) + 0.1 * face_jump_penalty(dF(V)), V)
    phi = V.dof_points[:, 2] - 0.3 * V.dof_points[:, 0] - 0.11
    assert relative_norm(S @ phi, np.abs(S).max() * np.abs(phi).max()) < 1e-12


# ----------------------------------------------------------------------------------------------
# user-written forms
# ----------------------------------------------------------------------------------------------


@bilinear_form(symmetric=True)
def helmholtz(u, v, w):
    return dot(u.tgrad, v.tgrad) + w.k2 * u * v


@bilinear_form
def helmholtz_plain(u, v, w):
    return dot(v.tgrad, u.tgrad) + (u - u / 2) * v * (2 * w.k2)


@pytest.mark.parametrize("which", ["meshed-torus", "cut-sphere"])
def test_user_helmholtz_form_matches_builtins(which):
    V = SMALL[which]()
    k2 = 3.7
    expected = (stiffness_matrix(V) + k2 * mass_matrix(V)).toarray()
    H = assemble(helmholtz * ds(V), V, k2=k2)
    assert isinstance(H, sp.csr_matrix)
    np.testing.assert_allclose(H.toarray(), expected, rtol=0, atol=1e-13 * np.abs(expected).max())
    plain = assemble(helmholtz_plain * ds(V), V, k2=k2)
    np.testing.assert_allclose(plain.toarray(), expected, rtol=0, atol=1e-13 * np.abs(expected).max())
    with pytest.raises(AttributeError, match="k2"):
        assemble(helmholtz * ds(V), V)


@pytest.mark.parametrize("which", ["meshed-torus", "cut-sphere"])
def test_symmetric_user_form_is_exactly_symmetric(which):
    V = SMALL[which]()
    H = assemble(helmholtz * ds(V), V, k2=3.7)
    assert (H - H.T).nnz == 0


@bilinear_form
def advection(u, v, w):
    beta = np.cross(w.omega, w.x)  # rotation field, made tangential to S_h below
    beta = beta - dot(beta, w.n)[..., None] * w.n
    return dot(beta, u.tgrad) * v


MASS3 = (np.ones((3, 3)) + np.eye(3)) / 12.0


def advection_reference(V, omega):
    """B_ij = int_{S_h} (P_h (omega x x)) . (P_h grad phi_j) phi_i, piece by piece, with
    int_t phi_i x = |t| sum_ab phi_i(v_a) (1 + delta_ab) / 12 v_b (exact: both are linear on t)."""
    n = V.n_dofs
    B = np.zeros((n, n))
    if isinstance(V, SurfaceP1Space):
        tri_pts = np.asarray(V.dof_points)[V.element_dofs]
        parents = np.arange(len(tri_pts))
    else:
        tri_pts, parents = V.cut.vertices[V.cut.triangles], V.cut.triangle_tets
    for P, e in zip(tri_pts, parents):
        c = np.cross(P[1] - P[0], P[2] - P[0])
        area, nrm = 0.5 * np.linalg.norm(c), c / np.linalg.norm(c)
        dofs = V.element_dofs[e]
        X = V.dof_points[dofs]
        if len(dofs) == 3:
            E = np.column_stack([X[1] - X[0], X[2] - X[0]])
            G = E @ np.linalg.inv(E.T @ E)
            grads = np.array([-G[:, 0] - G[:, 1], G[:, 0], G[:, 1]])
            vals = np.eye(3)  # the triangle is its own element
        else:
            Ti = np.linalg.inv(np.vstack([np.ones(4), X.T]))
            grads = Ti[:, 1:]
            vals = Ti[:, :1] + grads @ P.T
        tgrads = grads - np.outer(grads @ nrm, nrm)
        moments = area * vals @ MASS3 @ P  # (k, 3): int_t phi_i x
        B[np.ix_(dofs, dofs)] += np.cross(omega, moments) @ tgrads.T
    return B


@pytest.mark.parametrize("which", ["meshed-torus", "cut-sphere", "cut-torus"])
def test_user_advection_form_matches_reference(which):
    V = SMALL[which]()
    omega = np.array([0.2, -0.3, 1.0])
    B = assemble(advection * ds(V), V, omega=omega)
    ref = advection_reference(V, omega)
    scale = np.abs(ref).max()
    np.testing.assert_allclose(B.toarray(), ref, rtol=0, atol=1e-12 * scale)
    assert np.abs(B - B.T).max() > 0.1 * scale  # a genuinely non-symmetric form
    assert relative_norm(B @ np.ones(V.n_dofs), scale) < 1e-12  # no derivative of constants


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


@linear_form
def weighted(v, w):
    return w.a * v * w.x[..., 0]


@linear_form(degree=2)
def components(v, w):
    return v.value[..., None] * w.x  # (m, q, 3): the three coordinate loads at once


def test_user_linear_forms_match_load():
    V = SMALL["cut-sphere"]()
    np.testing.assert_allclose(assemble(weighted * ds(V), V, a=2.0), 2.0 * load_vector(V, lambda x: x[..., 0]), rtol=1e-13, atol=1e-16)
    np.testing.assert_allclose(assemble(components * ds(V), V), load_vector(V, lambda x: x, degree=2), rtol=1e-13, atol=1e-16)


def test_lattice_terms_that_go_elsewhere_allocate_nothing(monkeypatch):
    """The surface mass of a bulk field lives on other tets than the field's lattice: the form's
    LatticeSum gets no term, makes no slots and no matrix, and the result is the triangle route."""
    from cutfem.fem.assembly import LatticeSum
    from cutfem.fem.exact import _simplex_mass

    cut = cut_mesh(structured_box([-1, -1, -1], [1, 1, 1], cells=8), Sphere(0.7, [0.03, -0.01, 0.02]))
    W = CutP1Space(cut, NEG)
    made = []
    monkeypatch.setattr(LatticeSum, "matrix", lambda self: made.append(self) or pytest.fail("an empty LatticeSum was turned into a matrix"))
    M = assemble(mass(cut.ds()), W)
    reference = _simplex_mass(W, cut.triangle_points, W.local_elements(cut.ds(), cut.triangle_tets), cut.triangle_areas)
    assert not made and abs(M - reference).max() == 0
    one = np.ones(W.n_dofs)
    assert one @ M @ one == pytest.approx(cut.area, rel=1e-12)
