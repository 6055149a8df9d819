"""Closed forms and fast paths of the meshed (triangulated surface) pipeline.

Each fast path is checked against the general route it replaces: the same numbers up to
round-off, on meshes where nothing is special (perturbed and flipped tori, the icosahedral sphere).
"""

import numpy as np
import pytest

from cutfem.fem.norms import l2_error
from cutfem.geometry.shapes import Torus
from cutfem.fem.spaces import SurfaceP1Space
from cutfem.geometry.surface_meshes import sphere_mesh, torus_mesh


def test_torus_mean_curvature_vector_closed_form_matches_frame():
    tor = Torus(1.3, 0.45, center=[0.1, -0.2, 0.3])
    rng = np.random.default_rng(7)
    x = tor.center + rng.uniform(-1.8, 1.8, size=(4, 50, 3)) * [1, 1, 0.5]
    expected = tor.exact_mean_curvature(x)[..., None] * tor.exact_normal(x)
    np.testing.assert_allclose(tor.exact_mean_curvature_vector(x), expected, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(tor.exact_mean_curvature_vector(x), tor._careful_mean_curvature_vector(x), rtol=1e-14)
    far = np.array([[1e200, 2e200, 0.5]])  # squares overflow: the careful evaluation takes over
    np.testing.assert_array_equal(tor.exact_mean_curvature_vector(far), tor._careful_mean_curvature_vector(far))
    assert np.isfinite(tor.exact_mean_curvature_vector(far)).all()
    with pytest.raises(ValueError, match="axis"):
        tor.exact_mean_curvature_vector(tor.center + np.array([[0.0, 0.0, 0.2]]))
    with pytest.raises(ValueError, match="core circle"):
        tor.exact_mean_curvature_vector(tor.center + np.array([[1.3, 0.0, 0.0]]))
    with pytest.raises(ValueError, match="NaN"):
        tor.exact_mean_curvature_vector(np.array([[np.nan, 0.0, 0.0]]))


def _l2_by_quadrature(space, coeffs, exact, degree=4):
    """The general route: the quadrature of the measure, u_h from the P1 basis values."""
    ds = space.mesh.ds()
    quad = ds.quadrature(degree)
    d = np.asarray(exact(quad.points)) - space.evaluate(coeffs, ds, degree)
    d = d.reshape(d.shape[0], d.shape[1], -1)
    return np.sqrt(np.einsum("mqc,mqc,mq->", d, d, quad.weights))


@pytest.mark.parametrize("chunk", [1000, 1 << 12])
def test_l2_error_blocks_match_quadrature(chunk):
    space = SurfaceP1Space(torus_mesh(40, "perturbed-flipped", seed=3))
    tor = Torus()
    H = np.cos(3 * space.dof_points)  # vector valued
    expected = _l2_by_quadrature(space, H, tor.exact_mean_curvature_vector)
    assert l2_error(space, H, tor.exact_mean_curvature_vector, chunk=chunk) == pytest.approx(expected, rel=1e-13)
    u = np.sin(space.dof_points[:, 0])  # scalar, degree 6
    f = lambda x: x[..., 0] * x[..., 1]  # noqa: E731
    expected = _l2_by_quadrature(space, u, f, degree=6)
    assert l2_error(space, u, f, degree=6, chunk=chunk) == pytest.approx(expected, rel=1e-13)


# ----------------------------------------------------------------------------------------------
# topology by one sort, validation messages
# ----------------------------------------------------------------------------------------------

from cutfem.geometry.surface import SurfaceMesh  # noqa: E402
from cutfem.geometry.surface_checks import _halfedge_table, _pair_halfedges  # noqa: E402

MESHES = {
    "sphere": lambda: sphere_mesh(2),
    "torus-flipped": lambda: torus_mesh(12, "flipped", seed=4),
    "torus-perturbed-flipped": lambda: torus_mesh(14, "perturbed-flipped", seed=2),
}


@pytest.mark.parametrize("name", sorted(MESHES))
def test_one_sort_topology_matches_general_table(name):
    checked = MESHES[name]()
    plain = SurfaceMesh(checked.points, checked.triangles, check=False)  # lazily, by the general table
    edges, halfedge_edge, counts, forward = _halfedge_table(np.array(checked.triangles), checked.n_points)
    assert np.all(counts == 2)
    for mesh in (checked, plain):
        assert np.array_equal(mesh.edges, edges)
        assert np.array_equal(mesh.triangle_edges.reshape(-1), halfedge_edge)
        assert np.array_equal(mesh.edge_halfedges, _pair_halfedges(halfedge_edge, forward))
        # the vertex opposite each edge, in each of its two triangles
        tri = mesh.triangles[mesh.edge_triangles]  # (E, 2, 3)
        opp = mesh.edge_opposite_vertices
        assert np.all((tri == opp[:, :, None]).sum(axis=2) == 1)
        assert np.all(opp[:, :, None] != mesh.edges[:, None, :])


def test_flipped_components_keep_cross_products_consistent():
    sphere = sphere_mesh(1)
    mesh = SurfaceMesh(sphere.points, sphere.triangles[:, [0, 2, 1]])
    assert mesh.flipped_components == 1
    np.testing.assert_array_equal(mesh.normals, sphere.normals)
    np.testing.assert_array_equal(mesh.areas, sphere.areas)


def test_duplicate_of_opposite_orientation_rejected():
    # a two-triangle "pillow": every edge in exactly two triangles, consistently oriented
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])
    with pytest.raises(ValueError, match=r"1 triangle\(s\) duplicate another.*\(0, 1\)"):
        SurfaceMesh(points, [[0, 1, 2], [0, 2, 1]])
    # the same pillow beside a valid tetrahedron
    tet = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]) + 3
    points = np.concatenate([points, [[5, 0, 0], [6, 0, 0], [5, 1, 0], [5, 0, 1.0]]])
    with pytest.raises(ValueError, match=r"duplicate another"):
        SurfaceMesh(points, np.concatenate([tet, [[0, 1, 2], [0, 2, 1]]]))


def test_non_manifold_vertex_of_high_degree_rejected():
    # two icosahedral spheres glued at one node: a vertex with two fans of 5 triangles each
    a = sphere_mesh(0)
    touch = int(np.argmin(a.points[:, 0]))  # leftmost node of the copy b ...
    glue = int(np.argmax(a.points[:, 0]))  # ... moved onto the rightmost node of a
    b_points = a.points + (a.points[glue] - a.points[touch])
    keep = np.ones(len(a.points), bool)
    keep[touch] = False
    # b's nodes numbered after a's, its glued node replaced by a's
    new_index = np.full(len(a.points), -1)
    new_index[keep] = len(a.points) + np.arange(keep.sum())
    new_index[touch] = glue
    points = np.concatenate([a.points, b_points[keep]])
    triangles = np.concatenate([a.triangles, new_index[a.triangles]])
    with pytest.raises(ValueError, match=rf"non-manifold at 1 vertex.*nodes {glue}"):
        SurfaceMesh(points, triangles)


# ----------------------------------------------------------------------------------------------
# closed-form matrices on a triangulated surface against the general routes
# ----------------------------------------------------------------------------------------------

import scipy.sparse as sp  # noqa: E402

from cutfem.fem.assembly import SymmetricPattern  # noqa: E402
from cutfem.fem.closed_forms import _gradient_matrix, _jump_gram, _simplex_mass  # noqa: E402
from cutfem.fem.forms import assemble, bilinear_form  # noqa: E402
from cutfem.fem.terms import edge_jump_penalty, mass, tangential_stiffness  # noqa: E402

SPACES = {
    "sphere": lambda: SurfaceP1Space(sphere_mesh(2, 1.3, (0.1, 0.2, 0.3))),
    "torus-flipped": lambda: SurfaceP1Space(torus_mesh(16, "flipped", seed=5)),
    "torus-perturbed-flipped": lambda: SurfaceP1Space(torus_mesh(18, "perturbed-flipped", seed=6), h=0.05),
}


def _close(A, B, rel=1e-13):
    scale = abs(B).max()
    assert abs(A - B).max() <= rel * scale
    assert abs(A - A.T).max() == 0.0  # exactly symmetric
    assert A.has_canonical_format


@pytest.mark.parametrize("name", sorted(SPACES))
def test_closed_form_mass_is_the_quadrature_mass(name):
    space = SPACES[name]()
    ds = space.mesh.ds()
    M = assemble(mass(ds), space)
    vertices, parent, areas = space.surface_triangles()
    _close(M, _simplex_mass(space, vertices, parent, areas))
    quadrature_mass = assemble(bilinear_form(lambda u, v, w: u * v, symmetric=True, degree=2) * ds, space)
    _close(M, quadrature_mass)
    assert M.sum() == pytest.approx(space.mesh.area, rel=1e-14)


@pytest.mark.parametrize("name", sorted(SPACES))
def test_closed_form_stiffness_is_the_gradient_form(name):
    space = SPACES[name]()
    ds = space.mesh.ds()
    A = assemble(tangential_stiffness(ds), space)
    _close(A, _gradient_matrix(space, space.tangential_gradients_of, space.element_areas))
    stiffness = assemble(bilinear_form(lambda u, v, w: (u.tgrad * v.tgrad).sum(-1), symmetric=True, degree=0) * ds, space)
    _close(A, stiffness)
    assert np.abs(A @ np.ones(space.n_dofs)).max() < 1e-12 * abs(A).max()  # constants in the kernel


@pytest.mark.parametrize("name", sorted(SPACES))
def test_closed_form_edge_penalty_is_the_conormal_jump(name):
    space = SPACES[name]()
    ds = space.mesh.ds()
    J = assemble(edge_jump_penalty(ds), space)
    pairs, conormals, lengths = space.edges()
    _close(J, _jump_gram(space, pairs, conormals[:, 0], conormals[:, 1], 1.0, space.h * lengths))
    _close(assemble(edge_jump_penalty(ds, h=0.3), space), _jump_gram(space, pairs, conormals[:, 0], conormals[:, 1], 1.0, 0.3 * lengths))
    assert np.abs(J @ np.ones(space.n_dofs)).max() < 1e-12 * abs(J).max()


@pytest.mark.parametrize("name", sorted(SPACES))
def test_closed_forms_of_one_form_sum_into_one_pattern(name):
    """mass + c_1 stiffness + c_2 edge penalty assembled as one form (one PairSum, one CSR on the
    edge stencil) equals the sum of the three matrices assembled alone; a form without the edge
    penalty stays on the node graph (7 entries a row on a torus: n + 2 E with E = 3 n)."""
    space = SPACES[name]()
    ds = space.mesh.ds()
    M, A, J = (assemble(f, space) for f in (mass(ds), tangential_stiffness(ds), edge_jump_penalty(ds)))
    K = assemble(mass(ds) + 0.3 * tangential_stiffness(ds) + 0.1 * edge_jump_penalty(ds), space)
    _close(K, (M + 0.3 * A + 0.1 * J).tocsr(), rel=1e-15)
    assert K.nnz == space.edge_stencil_pattern().nnz and J.nnz == K.nnz
    MA = assemble(mass(ds) + 0.3 * tangential_stiffness(ds), space)
    _close(MA, (M + 0.3 * A).tocsr(), rel=1e-15)
    assert MA.nnz == M.nnz == A.nnz == space.node_pattern().nnz < K.nnz
    if name.startswith("torus"):
        assert M.nnz == 7 * space.n_dofs


def test_symmetric_pattern_sums_repeated_pairs():
    rng = np.random.default_rng(11)
    n = 40
    pairs = rng.integers(0, n, size=(400, 2))
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    diagonal, values = rng.random(n), rng.random(len(pairs))
    A = SymmetricPattern(pairs, n).matrix(diagonal, values)
    rows = np.concatenate([np.arange(n), pairs[:, 0], pairs[:, 1]])
    cols = np.concatenate([np.arange(n), pairs[:, 1], pairs[:, 0]])
    expected = sp.coo_matrix((np.concatenate([diagonal, values, values]), (rows, cols)), shape=(n, n)).toarray()
    np.testing.assert_allclose(A.toarray(), expected, rtol=1e-15, atol=0)
    B = A.copy()
    B.has_canonical_format = False
    B.sum_duplicates()
    assert np.array_equal(B.indices, A.indices) and np.array_equal(B.indptr, A.indptr)
    with pytest.raises(ValueError, match="two different"):
        SymmetricPattern([[1, 1]], 3)
    with pytest.raises(ValueError, match=r"in \[0, 3\)"):
        SymmetricPattern([[0, 3]], 3)
    with pytest.raises(ValueError, match="integer dof numbers"):
        SymmetricPattern(np.array([[0.5, 1.0]]), 3)
    with pytest.raises(ValueError, match=r"in \[0, 3\)"):  # checked before the narrowing to int32
        SymmetricPattern(np.array([[0, 2**32 + 1]]), 3)
    np.testing.assert_array_equal(SymmetricPattern([], 3).matrix(np.arange(3.0), np.zeros(0)).toarray(), np.diag(np.arange(3.0)))
    # the distinct pairs in lexicographic order, given as presorted: the same structure, no sums
    lo, hi = np.minimum(pairs[:, 0], pairs[:, 1]), np.maximum(pairs[:, 0], pairs[:, 1])
    unique = np.unique(np.column_stack([lo, hi]), axis=0)
    C = SymmetricPattern(unique, n, presorted=True)
    assert C.n_pairs == len(unique) < len(pairs)
    assert np.array_equal(C.indices, A.indices) and np.array_equal(C.indptr, A.indptr)
    summed = np.array([values[(lo == i) & (hi == j)].sum() for i, j in unique])
    np.testing.assert_allclose(C.matrix(diagonal, summed).toarray(), expected, rtol=1e-15, atol=0)
    with pytest.raises(ValueError, match="one value per pair"):
        SymmetricPattern(pairs, n).matrix(diagonal, values[:-1])
    with pytest.raises(ValueError, match=r"diagonal of shape \(40,\)"):
        C.matrix(diagonal[:-1], summed)


@pytest.mark.parametrize("family", ["structured", "flipped", "perturbed", "perturbed-flipped"])
def test_generated_torus_passes_the_full_validation(family):
    # torus_mesh checks only the geometry; the full validation must agree that nothing else is wrong
    generated = torus_mesh(10, family, seed=8)
    checked = SurfaceMesh(generated.points, generated.triangles)
    assert checked.flipped_components == 0
    assert np.array_equal(checked.triangles, generated.triangles)
    for name in ("edges", "edge_halfedges", "triangle_edges"):
        assert np.array_equal(getattr(checked, name), getattr(generated, name))
    np.testing.assert_array_equal(checked.normals, generated.normals)


def test_flipped_mesh_gives_the_same_matrices():
    # the edge dot products depend on the local vertex order: after the outward flip they are
    # recomputed, and the matrices are those of the mesh given outward
    sphere = sphere_mesh(2)
    flipped = SurfaceMesh(sphere.points, sphere.triangles[:, [0, 2, 1]])
    assert flipped.flipped_components == 1
    np.testing.assert_array_equal(flipped.triangle_edge_dots, sphere.triangle_edge_dots)
    a, b = SurfaceP1Space(sphere), SurfaceP1Space(flipped)
    for form in (mass, tangential_stiffness, edge_jump_penalty):
        assert abs(assemble(form(sphere.ds()), a) - assemble(form(flipped.ds()), b)).max() == 0.0


def test_l2_error_of_fortran_ordered_coefficients():
    # solvers may return (n, 3) solutions in Fortran order; same error as in C order
    space = SurfaceP1Space(torus_mesh(12, "perturbed", seed=1))
    H = np.cos(space.dof_points)
    f = Torus().exact_mean_curvature_vector
    assert l2_error(space, np.asfortranarray(H), f) == l2_error(space, H, f)
